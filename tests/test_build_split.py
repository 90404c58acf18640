"""`omg shards build`: a split by take (labels) and a seeded clip order, so that a shard is a fair
sample of the set rather than a run of one action."""

from __future__ import annotations

import pytest

from omg.data.datamodule import MotionDataModule
from omg.data.loaders import ClipDataset
from omg.errors import UsageError
from omg.tools.shards import build, shuffled


def _actions(shard_dir):
    dm = MotionDataModule(str(shard_dir))
    return [s["meta"]["labels"]["action"]
            for s in ClipDataset.from_shards(dm.train_urls, dm.feature_dim, dm.windows).samples]


def test_val_where_holds_out_the_labelled_takes(tmp_path):
    build("synth", tmp_path / "s", "humanml3d263", "smpl22", 20.0, options={"num_clips": 40},
          val_where={"action": ["walk", "jump"]})
    train, val = _actions(tmp_path / "s/train"), _actions(tmp_path / "s/val")
    assert val and set(val) <= {"walk", "jump"} and not {"walk", "jump"} & set(train)
    assert len(train) + len(val) == 40
    with pytest.raises(UsageError, match="not both"):
        build("synth", tmp_path / "t", "humanml3d263", "smpl22", 20.0, val_fraction=0.1, val_where={"action": ["walk"]})


def test_clips_are_written_in_a_seeded_random_order(tmp_path):
    items = list(range(100))
    a, b = list(shuffled(items, 16, seed=0)), list(shuffled(items, 16, seed=1))
    assert sorted(a) == items and a != items and a != b and a == list(shuffled(items, 16, seed=0))
    assert list(shuffled(items, 0, seed=0)) == items
    build("synth", tmp_path / "in_order", "humanml3d263", "smpl22", 20.0, options={"num_clips": 30})
    build("synth", tmp_path / "shuffled", "humanml3d263", "smpl22", 20.0, options={"num_clips": 30},
          shuffle_buffer=30, seed=3)
    in_order, mixed = _actions(tmp_path / "in_order"), _actions(tmp_path / "shuffled")
    assert sorted(in_order) == sorted(mixed) and in_order != mixed
