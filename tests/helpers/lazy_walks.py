"""A data source for build tests, registered on import: walks read lazily (in the build's helper
processes with --workers), with bad items, items of another domain and NaN clips among them."""

from __future__ import annotations

import gc
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from helpers import walking_clip
from omg.data.shards import LazyItem
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.tools.shards import build as build_shards

SOURCE = "test-lazy-walks"
FAIL_AT = 23


def _item(i: int, fps: float, fail_flag: str | None, delay: float = 0.0,
          readers: str | None = None, collect: bool = False) -> Clip | Exception | None:
    """Source item i, read lazily (in a helper process with --workers): a walk, a bad item, an
    item of another domain, or a clip whose features are NaN. ``readers``: a folder where each
    process that reads an item leaves a file named by its pid; ``collect``: the reading process's
    garbage collector runs first (as it may at any allocation)."""
    time.sleep(delay)
    if collect:
        gc.collect()
    if readers:
        (Path(readers) / str(os.getpid())).touch()
    if fail_flag and i == FAIL_AT and Path(fail_flag).exists():
        raise RuntimeError(f"interrupted at item {i}")  # stops the build, like a kill
    if i % 11 == 5:
        return ValueError(f"test bad item: number {i}")
    if i % 13 == 7:
        return None
    clip = walking_clip(i, fps)
    if i % 17 == 3:
        clip = replace(clip, positions=np.full_like(clip.positions, np.nan))  # fails to encode
    return replace(clip, id=f"clip{i:03d}", labels={"i": str(i)})


@DATA_SOURCES.register(SOURCE)
def lazy_walks(input, skeleton, fps, num_clips: int = 48, fail_flag: str | None = None,
               delay: float = 0.0, readers: str | None = None, collect: bool = False) -> list[LazyItem]:
    """Walks read when the build gets to them (a test source)."""
    return [LazyItem(_item, (i, fps, fail_flag, delay, readers, collect)) for i in range(num_clips)]


def build(out: Path, **kw) -> list:
    """The source's shards in ``out`` (train and a quarter val unless ``val_fraction`` says), 4 clips a shard."""
    options = kw.pop("options", {})
    kw.setdefault("val_fraction", 0.25)
    return build_shards(SOURCE, out, "humanml3d263", "smpl22", 20.0, max_clips=4, options=options, shuffle_buffer=16,
                 seed=3, **kw)
