"""OmniMotionGPT's data helpers: the animal categories' mean bone offsets, scanned from the shards'
meta alone (``PairedDataModule.category_offsets``, omg.data.paired, which also reads the human set
beside the animal one).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np


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
