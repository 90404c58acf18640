"""Source items as a build meets them: clips, ``LazyItem``s read where the build gets to them (possibly
in another process), and each one encoded into what a shard stores (``EncodedClip``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator

from omg.data.shards.schema import FeatureStats, encode_sample
from omg.motion import Clip, Representation


@dataclass(frozen=True)
class LazyItem:
    """A source item that is read when the build gets to it, possibly in a worker process.

    ``load(*args)`` returns a ``Clip``, ``None`` (nothing to import, e.g. a clip of another
    domain) or an exception (a bad item: counted as skipped); an exception it raises stops the
    build. With ``--workers`` the item travels to another process: ``load`` must be a
    module-level function and ``args`` picklable. Sources that list their files and yield one
    ``LazyItem`` per file are read in parallel; sources that yield clips are read in order by the
    main process and only encoded in parallel.
    """

    load: Callable[..., Clip | Exception | None]
    args: tuple = ()

    def __call__(self) -> Clip | Exception | None:
        return self.load(*self.args)


def resolved(items: Iterable) -> Iterator[Clip | Exception | None]:
    """A source's items with every ``LazyItem`` read: clips, exceptions and Nones."""
    for item in items:
        yield item() if isinstance(item, LazyItem) else item


@dataclass
class EncodedClip:
    """One clip, read and encoded: what ``ShardWriter.add`` stores (``error``: why it cannot be)."""

    id: str
    labels: dict
    key: str = ""
    files: dict[str, bytes] = field(default_factory=dict)
    stats: FeatureStats | None = None  # the sums over the clip's frames
    error: Exception | None = None


def encode_item(item, representation: Representation, fps: float) -> EncodedClip | Exception | None:
    """Read (a ``LazyItem``) and encode one source item; a bad clip comes back with its error."""
    if isinstance(item, LazyItem):
        item = item()
    if item is None or isinstance(item, Exception):
        return item
    try:
        if abs(item.fps - fps) > 1e-6:
            raise ValueError(f"clip {item.id!r} is at {item.fps} fps, the shard set at {fps}")
        key, files, features = encode_sample(item, representation)
    except (ValueError, OSError) as e:
        return EncodedClip(item.id, dict(item.labels), error=e)
    stats = FeatureStats()
    stats.add(features)
    return EncodedClip(item.id, dict(item.labels), key, files, stats)
