"""MotionDataModule: windows, collate, determinism, equal batch counts, bad samples, DDP split."""

from __future__ import annotations

import logging
import os
import socket
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from conftest import toy_clip, write_toy_shards
from omg.data.datamodule import MotionDataModule, StreamLoader, TooManyBadSamples
from omg.data.shards import Manifest
from omg.data.windows import WindowSampler
from omg.errors import UsageError


def _datamodule(shards, **kw):
    defaults = dict(batch_size=4, max_len=30, min_len=10, batches_per_epoch=6, num_workers=0, shuffle_buffer=8)
    return MotionDataModule(str(shards), **{**defaults, **kw})


def _epoch(loader):
    return [batch for batch in loader]


def test_windows_stay_inside_clips_and_within_bounds():
    w, rng = WindowSampler(max_len=50, min_len=20), np.random.default_rng(0)
    for T in (5, 20, 21, 49, 50, 51, 400):
        for _ in range(200):
            start, length = w.random(T, rng)
            assert 0 <= start and start + length <= T
            assert length == T if T <= 20 else 20 <= length <= min(50, T)
    assert w.center(400) == (175, 50) and w.center(30) == (0, 30)
    with pytest.raises(UsageError, match="min_len"):
        WindowSampler(max_len=10, min_len=20)


def test_batches_are_padded_masked_windows_of_the_clips(toy_shards):
    dm = _datamodule(toy_shards)
    m = Manifest.load(toy_shards)
    for batch in _epoch(dm.train_dataloader()):
        B, T, D = batch["motion"].shape
        assert B == 4 and D == 66 and T <= 30
        assert batch["mask"].sum(1).tolist() == batch["lengths"].tolist()
        assert (batch["motion"][~batch["mask"]] == 0).all()
        for b in range(B):
            index = int(batch["id"][b].split(".")[1])
            assert batch["text"][b] == f"caption {index}"
            n = int(batch["lengths"][b])
            window = batch["motion"][b, :n].numpy() * m.std + m.mean  # un-normalise
            clip = toy_clip(index).positions.reshape(-1, 66)
            starts = [s for s in range(len(clip) - n + 1) if np.allclose(clip[s : s + n], window, atol=1e-4)]
            assert starts, "a window must be a contiguous slice of its clip"


def test_stream_is_deterministic_for_a_seed(toy_shards):
    ids = lambda seed: [b["id"] for b in _epoch(_datamodule(toy_shards, seed=seed).train_dataloader())]
    assert ids(3) == ids(3)
    assert ids(3) != ids(4)


@pytest.mark.parametrize("num_workers", [0, 2])
def test_every_epoch_has_exactly_the_configured_batches(toy_shards, num_workers):
    loader = _datamodule(toy_shards, batches_per_epoch=7, num_workers=num_workers).train_dataloader()
    first, second = _epoch(loader), _epoch(loader)
    assert len(loader) == 7 and len(first) == len(second) == 7
    assert all(len(b["id"]) == 4 for b in first + second)
    assert [b["id"] for b in first] != [b["id"] for b in second]  # a new epoch, a new stream


def test_resumed_loader_continues_at_the_saved_position(toy_shards):
    loader = _datamodule(toy_shards, num_workers=2).train_dataloader()
    _epoch(loader)
    full = _epoch(loader)  # epoch 1
    partial = _datamodule(toy_shards, num_workers=2).train_dataloader()
    partial.load_state_dict({"epoch": 1, "batches_done": 4})
    rest = _epoch(partial)
    assert [b["id"] for b in rest] == [b["id"] for b in full[4:]]
    assert partial.state_dict() == {"epoch": 2, "batches_done": 0}


def test_corrupt_samples_are_skipped_with_a_warning(tmp_path, caplog):
    from test_shards import _rewrite_member

    shards = write_toy_shards(tmp_path / "s", num_clips=200, max_clips=100)
    for shard, key in zip(Manifest.load(shards).shard_paths, ("clip_0007", "clip_0107")):
        _rewrite_member(shard, f"{key}.motion.npy", b"garbage")
    with caplog.at_level(logging.WARNING):
        batches = _epoch(_datamodule(shards, batches_per_epoch=60, shuffle_buffer=2, max_bad_fraction=0.05).train_dataloader())
    assert len(batches) == 60
    assert not {"clip.0007", "clip.0107"} & {i for b in batches for i in b["id"]}
    warnings = [r.message for r in caplog.records]
    assert any("shard-000000.tar key clip_0007" in w or "shard-000001.tar key clip_0107" in w for w in warnings)


def test_too_many_corrupt_samples_stop_the_run(tmp_path):
    from test_shards import _rewrite_member

    shards = write_toy_shards(tmp_path / "s", num_clips=20, max_clips=20)
    for i in range(0, 20, 2):
        _rewrite_member(Manifest.load(shards).shard_paths[0], f"clip_{i:04d}.motion.npy", b"garbage")
    with pytest.raises(TooManyBadSamples, match="max_bad_fraction"):
        _epoch(_datamodule(shards, max_bad_fraction=0.1).train_dataloader())


def test_missing_shards_and_bad_settings_are_usage_errors(tmp_path):
    with pytest.raises(UsageError, match="no such directory"):
        MotionDataModule(str(tmp_path / "nope/shard-{000000..000003}.tar"))
    with pytest.raises(UsageError, match="no manifest.json"):
        MotionDataModule(str(tmp_path))
    shards = write_toy_shards(tmp_path / "s", num_clips=10, max_clips=10)
    with pytest.raises(UsageError, match="batch_size"):
        MotionDataModule(str(shards), batch_size=0)
    dm = _datamodule(shards)
    dm.trainer = SimpleNamespace(global_rank=0, world_size=2)
    with pytest.raises(UsageError, match="1 shards cannot be split disjointly across 2 ranks"):
        dm.train_dataloader()


def test_url_patterns_and_validation_set(toy_shards):
    pattern = str(toy_shards / "shard-{000000..000007}.tar")
    dm = MotionDataModule(pattern, val=str(toy_shards), batch_size=8, max_len=30, min_len=10, batches_per_epoch=2, num_workers=0)
    assert dm.feature_dim == 66 and dm.skeleton == "smpl22" and dm.fps == 20.0
    assert len(_epoch(dm.train_dataloader())) == 2
    val = _epoch(dm.val_dataloader())
    assert sum(len(b["id"]) for b in val) == 40
    assert _epoch(dm.val_dataloader())[0]["id"] == val[0]["id"]  # validation is fixed


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_main(rank, world, port, shards, start_method, out):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    torch.set_num_threads(1)
    dm = _datamodule(shards, batches_per_epoch=5, num_workers=2)
    dm.trainer = SimpleNamespace(global_rank=rank, world_size=world)  # what Lightning's trainer tells the datamodule
    base = dm.train_dataloader()
    loader = StreamLoader(base.dataset, num_workers=2, collate_fn=base.collate_fn, multiprocessing_context=start_method)
    ids = [i for batch in loader for i in batch["id"]]
    gathered = [None] * world
    dist.all_gather_object(gathered, {"rank": rank, "batches": len(ids) // 4, "ids": ids})
    if rank == 0:
        torch.save(gathered, out)
    dist.destroy_process_group()


def test_two_ranks_read_disjoint_shards_and_equal_batch_counts(tmp_path):
    # rank processes are spawned (nothing inherited), their loader workers forked
    shards = write_toy_shards(tmp_path / "s", num_clips=40, max_clips=5)  # 8 shards
    out = tmp_path / "gathered.pt"
    mp.spawn(_rank_main, args=(2, _free_port(), str(shards), "fork", str(out)), nprocs=2, join=True)
    r0, r1 = torch.load(out)
    assert r0["batches"] == r1["batches"] == 5
    shard_of = lambda clip_id: int(clip_id.split(".")[1]) // 5
    assert {shard_of(i) for i in r0["ids"]} <= {0, 2, 4, 6}
    assert {shard_of(i) for i in r1["ids"]} <= {1, 3, 5, 7}
    assert not set(r0["ids"]) & set(r1["ids"])
