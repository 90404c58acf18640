"""The shard sample schema: names, keys, how a clip becomes a sample and back, the per-feature
statistics a set keeps, and ``ShardError``, what every reader raises for a shard that fails a check."""

from __future__ import annotations

import io
import json
import re
from dataclasses import dataclass

import numpy as np

from omg.files import npy_bytes
from omg.motion import Clip, Representation

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
BUILD_STATE = "build-state.json"
SHARD_PATTERN = "shard-{:06d}.tar"
# A manifest's shard names: what the writer and `omg shards merge` write (SHARD_PATTERN). Nothing
# else is accepted: a pipe: set puts each name into its command, which a shell runs.
SHARD_NAME = re.compile(r"shard-[0-9]{6,}\.tar")
META_KEYS = ("id", "representation", "skeleton", "fps", "source", "labels", "category")


def sample_key(clip_id: str) -> str:
    """WebDataset splits keys at the first dot, so ids become dot-free keys."""
    return re.sub(r"[^A-Za-z0-9_\-]", "_", clip_id)


def encode_sample(clip: Clip, representation: Representation) -> tuple[str, dict[str, bytes], np.ndarray]:
    """One clip -> (key, {extension: bytes}, features).

    A clip's precomputed features are stored verbatim when they belong to ``representation``
    (so shards stay file-compatible with published feature files); otherwise it is encoded.
    """
    if clip.features is not None and clip.features_representation == representation.name:
        features, extra = clip.features, {}
    else:
        features, extra = representation.encode(clip)
    features = np.ascontiguousarray(features, dtype=np.float32)
    if features.ndim != 2 or features.shape[1] != representation.dim or len(features) == 0:
        raise ValueError(f"clip {clip.id!r}: encoded to shape {features.shape}, expected (T>0, {representation.dim})")
    if not np.isfinite(features).all():
        raise ValueError(f"clip {clip.id!r}: features contain NaN or inf")
    meta = {
        "id": clip.id,
        "representation": representation.name,
        "skeleton": representation.skeleton.name,
        "fps": clip.fps,
        "source": clip.source,
        "labels": clip.labels,
        "category": clip.category,
        **extra,
    }
    files = {
        "motion.npy": npy_bytes(features),
        "meta.json": json.dumps(meta).encode(),
        "texts.json": json.dumps(list(clip.texts)).encode(),
    }
    return sample_key(clip.id), files, features


@dataclass
class FeatureStats:
    """Running per-feature sums in float64, mergeable across shards."""

    count: int = 0
    total: np.ndarray | None = None
    total_sq: np.ndarray | None = None

    def add(self, features: np.ndarray) -> None:
        f = features.astype(np.float64)
        if self.total is None:
            self.total, self.total_sq = np.zeros(f.shape[1]), np.zeros(f.shape[1])
        self.count += len(f)
        self.total += f.sum(0)
        self.total_sq += (f * f).sum(0)

    def merge(self, other: FeatureStats) -> None:
        if other.total is None:
            return
        if self.total is None:
            self.total, self.total_sq = np.zeros_like(other.total), np.zeros_like(other.total)
        self.count += other.count
        self.total += other.total
        self.total_sq += other.total_sq

    def mean_std(self) -> tuple[np.ndarray, np.ndarray]:
        mean = self.total / self.count
        var = np.maximum(self.total_sq / self.count - mean * mean, 0.0)
        return mean, np.sqrt(var)

    def to_json(self) -> dict:
        return {"count": self.count, "total": self.total.tolist(), "total_sq": self.total_sq.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> FeatureStats:
        return cls(d["count"], np.asarray(d["total"]), np.asarray(d["total_sq"]))


def decode_sample(raw: dict[str, bytes], feature_dim: int | None = None) -> dict:
    """Raw tar members of one sample -> {"motion", "meta", "texts", "key"}; raises ValueError."""
    missing = [ext for ext in ("motion.npy", "meta.json", "texts.json") if ext not in raw]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    motion = np.load(io.BytesIO(raw["motion.npy"]), allow_pickle=False)
    if motion.dtype != np.float32 or motion.ndim != 2 or len(motion) == 0:
        raise ValueError(f"motion.npy is {motion.dtype} {motion.shape}, expected float32 (T>0, D)")
    if feature_dim is not None and motion.shape[1] != feature_dim:
        raise ValueError(f"motion.npy has {motion.shape[1]} features, the manifest says {feature_dim}")
    if not np.isfinite(motion).all():
        raise ValueError("motion.npy contains NaN or inf")
    meta = json.loads(raw["meta.json"])
    if missing := [k for k in META_KEYS if k not in meta]:
        raise ValueError(f"meta.json lacks {', '.join(missing)}")
    texts = json.loads(raw["texts.json"])
    if not isinstance(texts, list) or not all(isinstance(t, str) for t in texts):
        raise ValueError("texts.json is not a list of strings")
    return {"key": raw.get("__key__", meta["id"]), "motion": motion, "meta": meta, "texts": texts}


SHARD_CHECKS = ("file", "size", "readable", "samples", "end-of-archive", "sha256")
_END_OF_ARCHIVE = b"\0" * 1024  # two zero blocks end every tar
_COMPRESSED_MAGIC = (b"\x1f\x8b", b"BZh", b"\xfd7zXZ", b"\x28\xb5\x2f\xfd")


class ShardError(ValueError):
    """A shard that is missing, unreadable, or does not match what its manifest records.

    ``shard``: the path or URL; ``check``: which check failed, one of ``SHARD_CHECKS``
    (``file`` missing, ``size`` bytes differ, ``readable`` the tar is broken, ``samples`` the
    sample count differs, ``end-of-archive`` the tar lacks its closing zero blocks, ``sha256``
    the bytes are garbled or replaced); ``reason``: what was found, e.g. "truncated: 3 of 5
    samples". ``str(e)`` is ``"<shard>: <reason>"``.
    """

    def __init__(self, shard: str, check: str = "readable", reason: str = ""):
        super().__init__(f"{shard}: {reason}" if reason else str(shard))
        self.shard, self.check, self.reason = str(shard), check, reason or str(shard)

    def __reduce__(self):  # keep the fields through pickling (DataLoader workers)
        return type(self), (self.shard, self.check, self.reason)
