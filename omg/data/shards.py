"""WebDataset shards of encoded motion: the sample schema, an atomic resumable writer, the
manifest, and validation.

A shard set is a directory of ``shard-NNNNNN.tar`` files plus ``manifest.json``. Each sample
is one clip stored under a key without dots:

- ``<key>.motion.npy``: float32 (T, D) features of the set's representation;
- ``<key>.meta.json``: id, representation, skeleton, fps, source, labels, category, and
  per-clip quantities the representation needs (bone offsets);
- ``<key>.texts.json``: a list of captions, empty for unlabeled data.

Shards are written under a temporary name and renamed when complete, so a shard file that
exists is whole. ``build-state.json`` records the finished shards with the source position
and feature statistics they cover; an interrupted build resumes after the last of them.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import tarfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from omg.errors import UsageError
from omg.motion import Clip, Representation

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
BUILD_STATE = "build-state.json"
SHARD_PATTERN = "shard-{:06d}.tar"
META_KEYS = ("id", "representation", "skeleton", "fps", "source", "labels", "category")


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed over ``path`` when the block ends
    without error, so readers see the old file or the whole new one, never a part.

    The temporary name keeps the suffix (writers such as Pillow choose the format by it).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json(path: Path, obj) -> None:
    atomic_write(path, (json.dumps(obj, indent=1) + "\n").encode())


def sample_key(clip_id: str) -> str:
    """WebDataset splits keys at the first dot, so ids become dot-free keys."""
    return re.sub(r"[^A-Za-z0-9_\-]", "_", clip_id)


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


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


def _tar_bytes(samples: list[tuple[str, dict[str, bytes]]]) -> bytes:
    """A deterministic tar (fixed mtime/owner) so rebuilding the same data gives the same bytes."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for key, files in samples:
            for ext, data in files.items():
                info = tarfile.TarInfo(f"{key}.{ext}")
                info.size, info.mtime, info.mode = len(data), 0, 0o644
                info.uname = info.gname = "omg"
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


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


@dataclass
class SourceItems:
    """What a source may return instead of a bare iterator, to pass set-level facts along.

    ``stats`` maps a representation name to a published (mean, std) pair, each (D,); a shard
    set of that representation stores them in its manifest instead of the measured ones, so
    models normalise exactly as the published ones do (HumanML3D's ``Mean.npy``/``Std.npy``).
    """

    items: Iterable[Clip | Exception]
    stats: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def __iter__(self) -> Iterator[Clip | Exception]:
        return iter(self.items)


@dataclass
class BuildSummary:
    out_dir: Path
    clips: int = 0
    frames: int = 0
    shards: int = 0
    resumed_shards: int = 0
    skipped: dict[str, int] = field(default_factory=dict)

    def __str__(self) -> str:
        skipped = sum(self.skipped.values())
        reasons = ", ".join(f"{k}: {v}" for k, v in sorted(self.skipped.items()))
        return (
            f"{self.out_dir}: {self.clips} clips, {self.frames} frames in {self.shards} shards"
            f" ({self.resumed_shards} kept from an earlier run); skipped {skipped}"
            + (f" ({reasons})" if reasons else "")
        )


class ShardWriter:
    """Writes clips into shards of at most ``max_clips`` clips or ``max_bytes`` bytes.

    Clips come from a source iterator whose order is deterministic; the build state records
    how many source items each finished shard consumed, so a resumed build skips exactly
    those. Bad clips (the encoder raises ``ValueError``) are skipped and counted by reason.
    ``stats``: a fixed (mean, std) for the manifest instead of the one measured on the clips.
    """

    def __init__(
        self,
        out_dir: str | Path,
        representation: Representation,
        fps: float,
        max_clips: int = 1000,
        max_bytes: int = 256 << 20,
        command: str = "",
        log=print,
        stats: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        if max_clips < 1 or max_bytes < 1:
            raise UsageError(f"shard size must be positive, got max_clips={max_clips}, max_bytes={max_bytes}")
        if stats is not None:
            stats = tuple(np.asarray(a, dtype=np.float32).reshape(-1) for a in stats)
            if any(len(a) != representation.dim for a in stats) or not (stats[1] > 0).all():
                raise UsageError(
                    f"fixed stats for {representation.name!r} must be a mean and a positive std of "
                    f"{representation.dim} features each, got shapes {[a.shape for a in stats]}"
                )
        self.stats = stats
        self.out_dir = Path(out_dir)
        self.representation = representation
        self.fps = fps
        self.max_clips, self.max_bytes = max_clips, max_bytes
        self.command = command
        self.log = log

    def _load_state(self) -> dict:
        path = self.out_dir / BUILD_STATE
        if not path.exists():
            return {"shards": [], "skipped": {}}
        state = json.loads(path.read_text())
        expected = {"representation": self.representation.name, "fps": self.fps}
        found = {k: state.get(k) for k in expected}
        if found != expected:
            raise UsageError(
                f"{self.out_dir} holds an unfinished build with {found}, not {expected}; "
                "use the same settings to resume or choose another output directory"
            )
        # shards beyond the recorded state were never finished: remove them
        for extra in sorted(self.out_dir.glob("shard-*.tar"))[len(state["shards"]) :]:
            extra.unlink()
        return state

    def write(self, items: Iterable[Clip | Exception | None]) -> BuildSummary:
        """Consume the source: clips, exceptions for items that failed to load, and None for
        items that belong to another split."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for stale in self.out_dir.glob(".*.tmp*"):
            stale.unlink()
        state = self._load_state()
        state.update(representation=self.representation.name, fps=self.fps)
        summary = BuildSummary(self.out_dir, resumed_shards=len(state["shards"]))
        skipped: dict[str, int] = state["skipped"]
        done_items = state["shards"][-1]["source_end"] if state["shards"] else 0
        seen_keys = set(state.get("keys", []))

        pending: list[tuple[str, dict[str, bytes]]] = []
        pending_bytes, pending_stats = 0, FeatureStats()
        position = 0

        def flush() -> None:
            nonlocal pending, pending_bytes, pending_stats
            index = len(state["shards"])
            name = SHARD_PATTERN.format(index)
            data = _tar_bytes(pending)
            atomic_write(self.out_dir / name, data)
            state["shards"].append(
                {
                    "name": name,
                    "clips": len(pending),
                    "frames": pending_stats.count,
                    "bytes": len(data),
                    "sha256": hashlib.sha256(data).hexdigest(),
                    "source_end": position,
                    "stats": pending_stats.to_json(),
                }
            )
            state["keys"] = sorted(seen_keys)
            write_json(self.out_dir / BUILD_STATE, state)
            self.log(f"wrote {name}: {len(pending)} clips")
            pending, pending_bytes, pending_stats = [], 0, FeatureStats()

        for position, item in enumerate(items, start=1):
            if position <= done_items or item is None:
                continue
            try:
                if isinstance(item, Exception):
                    raise item
                if abs(item.fps - self.fps) > 1e-6:
                    raise ValueError(f"clip {item.id!r} is at {item.fps} fps, the shard set at {self.fps}")
                key, files, features = encode_sample(item, self.representation)
                if key in seen_keys:
                    raise ValueError(f"duplicate clip id {item.id!r}")
            except (ValueError, OSError) as e:
                reason = type(e).__name__ if not str(e) else str(e).split(":")[0][:60]
                skipped[reason] = skipped.get(reason, 0) + 1
                self.log(f"skipped source item {position}: {e}")
                continue
            seen_keys.add(key)
            pending.append((key, files))
            pending_bytes += sum(len(b) for b in files.values())
            pending_stats.add(features)
            if len(pending) >= self.max_clips or pending_bytes >= self.max_bytes:
                flush()
        if pending:
            flush()
        if not state["shards"]:
            raise UsageError(f"no clip could be written to {self.out_dir} ({skipped or 'the source was empty'})")

        self._write_manifest(state)
        (self.out_dir / BUILD_STATE).unlink()
        summary.shards = len(state["shards"])
        summary.clips = sum(s["clips"] for s in state["shards"])
        summary.frames = sum(s["frames"] for s in state["shards"])
        summary.skipped = skipped
        return summary

    def _write_manifest(self, state: dict) -> None:
        stats = FeatureStats()
        for shard in state["shards"]:
            stats.merge(FeatureStats.from_json(shard["stats"]))
        mean, std = self.stats or self.representation.finalize_stats(*stats.mean_std())
        skeleton = self.representation.skeleton
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "representation": self.representation.name,
            "feature_dim": self.representation.dim,
            "skeleton": skeleton.name,
            "skeleton_def": skeleton.to_dict(),
            "fps": self.fps,
            "num_clips": sum(s["clips"] for s in state["shards"]),
            "num_frames": stats.count,
            "num_shards": len(state["shards"]),
            "skipped": state["skipped"],
            "shards": [{k: s[k] for k in ("name", "clips", "frames", "bytes", "sha256")} for s in state["shards"]],
            "mean": mean.tolist(),
            "std": std.tolist(),
            "stats_origin": "source" if self.stats else "measured",
            "command": self.command,
        }
        write_json(self.out_dir / MANIFEST, manifest)


@dataclass
class Manifest:
    """The parsed ``manifest.json`` of a shard set."""

    path: Path
    data: dict

    @classmethod
    def load(cls, shard_dir: str | Path) -> Manifest:
        path = Path(shard_dir) / MANIFEST
        if not path.exists():
            hint = " (an unfinished build: run the same build command again)" if (path.parent / BUILD_STATE).exists() else ""
            raise UsageError(f"no {MANIFEST} in {path.parent}{hint}; build shards with `omg shards build` or `omg shards synth`")
        data = json.loads(path.read_text())
        if data.get("schema_version") != SCHEMA_VERSION:
            raise UsageError(f"{path}: schema version {data.get('schema_version')}, this omg reads {SCHEMA_VERSION}; rebuild the shards")
        return cls(path, data)

    @property
    def dir(self) -> Path:
        return self.path.parent

    @property
    def shard_paths(self) -> list[Path]:
        return [self.dir / s["name"] for s in self.data["shards"]]

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.data["mean"], dtype=np.float32)

    @property
    def std(self) -> np.ndarray:
        return np.asarray(self.data["std"], dtype=np.float32)

    def __getitem__(self, key: str):
        return self.data[key]

    def spec(self) -> dict:
        """What a model needs to know about its data, stored in its checkpoint."""
        return {k: self.data[k] for k in ("representation", "skeleton", "fps", "feature_dim", "mean", "std")}

    def summary(self) -> str:
        d = self.data
        hours = d["num_frames"] / d["fps"] / 3600
        return (
            f"{self.dir}: {d['num_clips']} clips, {d['num_frames']} frames ({hours:.2f} h at {d['fps']} fps) "
            f"in {d['num_shards']} shards; representation {d['representation']} ({d['feature_dim']}-d) "
            f"on {d['skeleton']}; built by: {d['command'] or 'unknown'}"
        )


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


def iter_tar(path: str | Path) -> Iterator[dict[str, bytes]]:
    """Raw samples (``{"__key__", ext: bytes}``) of one tar, grouped by key like WebDataset."""
    import webdataset as wds

    stream = wds.gopen(str(path))
    try:
        files = wds.tariterators.tar_file_expander([{"url": str(path), "stream": stream}])
        for sample in wds.tariterators.group_by_keys(files):
            sample.pop("__url__", None)
            yield sample
    finally:
        stream.close()


def validate(shard_dir: str | Path) -> tuple[Manifest, int, list[str]]:
    """Decode every sample; returns (manifest, good sample count, problems as 'shard key: reason')."""
    manifest = Manifest.load(shard_dir)
    problems, good = [], 0
    for entry, path in zip(manifest["shards"], manifest.shard_paths):
        if not path.exists():
            problems.append(f"{path.name}: missing")
            continue
        count = 0
        try:
            for raw in iter_tar(path):
                count += 1
                try:
                    decode_sample(raw, manifest["feature_dim"])
                    good += 1
                except (ValueError, KeyError) as e:
                    problems.append(f"{path.name} {raw.get('__key__')}: {e}")
        except Exception as e:  # noqa: BLE001 - a broken tar is reported, not raised
            problems.append(f"{path.name}: unreadable after {count} samples ({type(e).__name__}: {e})")
            continue
        if count != entry["clips"]:
            problems.append(f"{path.name}: {count} samples, the manifest says {entry['clips']}")
    return manifest, good, problems
