"""OmniMotionGPT's data helpers: the animal categories' mean bone offsets, scanned from the shards'
meta alone (``PairedDataModule.category_offsets``, omg.data.paired, which also reads the human set
beside the animal one), and the checks of what its two shard sets hold.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np

from omg.errors import UsageError
from omg.motion import DataSpec


def category_offsets(samples: Sequence[dict]) -> dict[str, list[list[float]]]:
    """Mean bone offsets (J, 3) per category of decoded samples' meta."""
    sums: dict[str, tuple[np.ndarray, int]] = {}
    for meta in samples:
        if meta.get("offsets") is None:
            continue
        name = meta.get("category") or "animal"
        total, count = sums.get(name, (0.0, 0))
        sums[name] = (total + np.asarray(meta["offsets"], dtype=np.float64), count + 1)
    return {name: (total / count).round(6).tolist() for name, (total, count) in sorted(sums.items())}


def scan_metas(urls: Sequence[str]) -> list[dict]:
    """Every sample's meta.json of the shards (motion is not decoded)."""
    from omg.data.shards import iter_tar

    return [json.loads(raw["meta.json"]) for url in urls for raw in iter_tar(url) if "meta.json" in raw]


def check_maa(spec: DataSpec, key: str, skeleton: str) -> None:
    """UsageError unless ``spec`` is ``skeleton`` motion in the maa representation."""
    if spec.representation != "maa" or spec.skeleton != skeleton:
        raise UsageError(f"{key}: OmniMotionGPT reads {skeleton} shards in the maa representation, got "
                         f"{spec.skeleton} {spec.representation} (build them with `omg shards build ... --skeleton "
                         f"{skeleton} --representation maa`)")


def check_same_stats(found: DataSpec, stored: DataSpec) -> None:
    """The human stream's batches are normalised with its shards' statistics and un-normalised with the
    checkpoint's (``human_spec``): a run that goes on from a checkpoint must read human shards like those."""
    stored.check_compatible(found, "the checkpoint's human data", "data.human")
    if found.mean != stored.mean or found.std != stored.std:
        raise UsageError("data.human: its shards' mean/std differ from those the checkpoint was trained with "
                         "(human_spec); go on from this checkpoint with the same human shards")
