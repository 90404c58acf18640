"""``ShardWriter``: clips into shards of bounded size, each written under a temporary name and renamed
when complete; ``build-state.json`` records the finished shards, so an interrupted build resumes."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from omg.data.shards.items import EncodedClip, LazyItem, encode_item
from omg.data.shards.manifest import manifest_data
from omg.data.shards.schema import BUILD_STATE, MANIFEST, SHARD_PATTERN, FeatureStats
from omg.errors import UsageError
from omg.files import atomic_write, write_json
from omg.motion import Clip, Representation


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

    ``write(items)`` reads, encodes and writes in one go; ``write_shards`` drives one or more
    writers through ``open`` / ``add`` / ``close`` (a train/val split in one pass, workers).
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

    def write(self, items: Iterable[Clip | LazyItem | Exception | None]) -> BuildSummary:
        """Consume the source: clips (or ``LazyItem``s), exceptions for items that failed to
        load, and None for items that belong to another split."""
        done = self.open()
        for position, item in enumerate(items, start=1):
            self.add(position, None if position <= done else encode_item(item, self.representation, self.fps))
        return self.close()

    def open(self) -> int:
        """Start or resume: returns the source position the finished shards cover."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for stale in self.out_dir.glob(".*.tmp*"):
            stale.unlink()
        self._state = state = self._load_state()
        state.update(representation=self.representation.name, fps=self.fps)
        self._resumed = len(state["shards"])
        self._done = state["shards"][-1]["source_end"] if state["shards"] else 0
        self._seen = set(state.get("keys", []))
        self._pending: list[tuple[str, dict[str, bytes]]] = []
        self._pending_bytes, self._pending_stats = 0, FeatureStats()
        self._position = self._done
        return self._done

    def add(self, position: int, result: EncodedClip | Exception | None) -> None:
        """The source item at ``position`` (1-based, increasing): an encoded clip, the exception
        of an item that failed, or None (nothing for this writer)."""
        self._position = max(self._position, position)
        if position <= self._done or result is None:
            return
        error = result if isinstance(result, Exception) else result.error
        if error is None and result.key in self._seen:
            error = ValueError(f"duplicate clip id {result.id!r}")
        if error is not None:
            reason = type(error).__name__ if not str(error) else str(error).split(":")[0][:60]
            skipped = self._state["skipped"]
            skipped[reason] = skipped.get(reason, 0) + 1
            self.log(f"skipped source item {position}: {error}")
            return
        self._seen.add(result.key)
        self._pending.append((result.key, result.files))
        self._pending_bytes += sum(len(b) for b in result.files.values())
        self._pending_stats.merge(result.stats)
        if len(self._pending) >= self.max_clips or self._pending_bytes >= self.max_bytes:
            self._flush()

    def _flush(self) -> None:
        state = self._state
        name = SHARD_PATTERN.format(len(state["shards"]))
        data = _tar_bytes(self._pending)
        atomic_write(self.out_dir / name, data)
        state["shards"].append(
            {
                "name": name,
                "clips": len(self._pending),
                "frames": self._pending_stats.count,
                "bytes": len(data),
                "sha256": hashlib.sha256(data).hexdigest(),
                "source_end": self._position,
                "stats": self._pending_stats.to_json(),
            }
        )
        state["keys"] = sorted(self._seen)
        write_json(self.out_dir / BUILD_STATE, state)
        self.log(f"wrote {name}: {len(self._pending)} clips")
        self._pending, self._pending_bytes, self._pending_stats = [], 0, FeatureStats()

    def close(self) -> BuildSummary:
        """Write the last shard and the manifest; the build state goes."""
        if self._pending:
            self._flush()
        state = self._state
        if not state["shards"]:
            why = f"none of the {self._position} source items went to it" if self._position else "the source was empty"
            raise UsageError(f"no clip could be written to {self.out_dir} ({state['skipped'] or why})")
        self._write_manifest(state)
        (self.out_dir / BUILD_STATE).unlink()
        return BuildSummary(
            self.out_dir,
            clips=sum(s["clips"] for s in state["shards"]),
            frames=sum(s["frames"] for s in state["shards"]),
            shards=len(state["shards"]),
            resumed_shards=self._resumed,
            skipped=state["skipped"],
        )

    def _write_manifest(self, state: dict) -> None:
        stats = FeatureStats()
        for shard in state["shards"]:
            stats.merge(FeatureStats.from_json(shard["stats"]))
        shards = [{k: s[k] for k in ("name", "clips", "frames", "bytes", "sha256")} for s in state["shards"]]
        manifest = manifest_data(self.representation, self.fps, shards, stats, state["skipped"], self.command,
                                 self.stats)
        write_json(self.out_dir / MANIFEST, manifest)
