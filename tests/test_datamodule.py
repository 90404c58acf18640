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

from helpers import rewrite_member, toy_clip, write_toy_shards
from helpers.forked import spawn_ranks
from omg.data.datamodule import MotionDataModule
from omg.data.loaders import StreamLoader, TooManyBadSamples
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
    def ids(seed):
        return [b["id"] for b in _epoch(_datamodule(toy_shards, seed=seed).train_dataloader())]

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
    assert partial.state_dict() == {"epoch": 1, "batches_done": 6}
    # a position at an epoch's end resumes at the next epoch's start, skipping nothing
    after = _datamodule(toy_shards, num_workers=2).train_dataloader()
    after.load_state_dict(partial.state_dict())
    assert [b["id"] for b in _epoch(after)] == [b["id"] for b in _epoch(loader)]


def _counting_reads(monkeypatch) -> list[str]:
    """The shard urls the stream reads from their bytes, in order (a data process of its own, num_workers 0)."""
    import omg.data.loaders as loaders

    reads, read_shard = [], loaders.read_shard

    def counted(url, expected):
        reads.append(url)
        return read_shard(url, expected)

    monkeypatch.setattr(loaders, "read_shard", counted)
    return reads


def test_a_small_set_is_decoded_once_and_gives_the_same_batches(toy_shards, monkeypatch):
    """data.cache_mb: the 8 toy shards fit, so each is read and decoded once, and two epochs are the
    batches of a stream that reads every draw from the bytes (cache_mb 0) or whose set is over the cap."""
    reads = _counting_reads(monkeypatch)
    epochs = {}
    for name, cache_mb in (("kept", 512.0), ("read", 0.0), ("over", 0.001)):  # the set's motion: 0.02 MiB
        reads.clear()
        loader = _datamodule(toy_shards, batches_per_epoch=20, cache_mb=cache_mb).train_dataloader()
        epochs[name] = _epoch(loader) + _epoch(loader)
        epochs[name + " reads"] = list(reads)
    shards = len(Manifest.load(toy_shards).shard_paths)
    assert sorted(epochs["kept reads"]) == sorted(set(epochs["read reads"])) and len(epochs["kept reads"]) == shards
    assert len(epochs["read reads"]) > 3 * shards and epochs["over reads"] == epochs["read reads"]
    for name in ("read", "over"):
        for mine, theirs in zip(epochs["kept"], epochs[name], strict=True):
            assert mine["id"] == theirs["id"] and mine["text"] == theirs["text"]
            assert torch.equal(mine["motion"], theirs["motion"]) and torch.equal(mine["mask"], theirs["mask"])


def test_a_shard_with_a_bad_sample_is_read_again_and_its_skips_counted(tmp_path, monkeypatch, caplog):
    shards = write_toy_shards(tmp_path / "s", num_clips=20, max_clips=5)
    bad_shard = Manifest.load(shards).shard_paths[0]
    rewrite_member(bad_shard, "clip_0002.motion.npy", b"garbage")
    reads = _counting_reads(monkeypatch)
    with caplog.at_level(logging.WARNING):
        _epoch(_datamodule(shards, batches_per_epoch=30, shuffle_buffer=2, max_bad_fraction=0.5,
                           verify_shards=False).train_dataloader())
    bad_reads = reads.count(str(bad_shard))
    assert bad_reads > 1 and all(reads.count(url) == 1 for url in set(reads) - {str(bad_shard)})
    skips = [r.getMessage() for r in caplog.records if "clip_0002" in r.getMessage()]
    assert len(skips) == bad_reads and f"({bad_reads} bad of " in skips[-1], skips  # each read counts it again


def test_corrupt_samples_are_skipped_with_a_warning(tmp_path, caplog):
    shards = write_toy_shards(tmp_path / "s", num_clips=200, max_clips=100)
    for shard, key in zip(Manifest.load(shards).shard_paths, ("clip_0007", "clip_0107")):
        rewrite_member(shard, f"{key}.motion.npy", b"garbage")
    with caplog.at_level(logging.WARNING):
        batches = _epoch(_datamodule(shards, batches_per_epoch=60, shuffle_buffer=2, max_bad_fraction=0.05,
                                     verify_shards=False).train_dataloader())
    assert len(batches) == 60
    assert not {"clip.0007", "clip.0107"} & {i for b in batches for i in b["id"]}
    warnings = [r.message for r in caplog.records]
    assert any("shard-000000.tar key clip_0007" in w or "shard-000001.tar key clip_0107" in w for w in warnings)


def test_too_many_corrupt_samples_stop_the_run(tmp_path):
    shards = write_toy_shards(tmp_path / "s", num_clips=20, max_clips=20)
    for i in range(0, 20, 2):
        rewrite_member(Manifest.load(shards).shard_paths[0], f"clip_{i:04d}.motion.npy", b"garbage")
    with pytest.raises(TooManyBadSamples, match="max_bad_fraction"):
        _epoch(_datamodule(shards, max_bad_fraction=0.1, verify_shards=False).train_dataloader())


def _garble(shard, offset_from_end=2000):
    data = bytearray(shard.read_bytes())
    data[-offset_from_end] ^= 0xFF  # inside the last sample's payload: the tar still parses
    shard.write_bytes(bytes(data))


def test_shards_that_fail_verification_are_skipped_whole(tmp_path, caplog):
    """Garbled bytes and a tar cut at a header boundary parse as valid tars; the manifest's
    sha256, size and sample count catch them before any of their samples is trained on."""
    shards = write_toy_shards(tmp_path / "s", num_clips=60, max_clips=5)  # 12 shards
    paths = Manifest.load(shards).shard_paths
    _garble(paths[0])
    cut = paths[1].read_bytes()
    paths[1].write_bytes(cut[: 512 * (len(cut) // 1024)])  # a header boundary, half the shard
    with caplog.at_level(logging.WARNING):
        batches = _epoch(_datamodule(shards, batches_per_epoch=30, max_bad_fraction=0.5).train_dataloader())
    seen = {int(i.split(".")[1]) for b in batches for i in b["id"]}
    assert len(batches) == 30 and seen and not seen & set(range(10))  # nothing of shards 0 and 1
    warnings = " ".join(r.getMessage() for r in caplog.records)
    assert "shard-000000.tar" in warnings and "sha256" in warnings
    assert "shard-000001.tar" in warnings
    # unverified, the garbled shard's samples would be trained on
    unverified = _epoch(_datamodule(shards, batches_per_epoch=30, max_bad_fraction=0.5,
                                     verify_shards=False).train_dataloader())
    assert {int(i.split(".")[1]) for b in unverified for i in b["id"]} & set(range(5))


def test_bad_validation_shards_are_counted_and_stop_past_the_limit(tmp_path, caplog):
    shards = write_toy_shards(tmp_path / "s", num_clips=20, max_clips=5)
    _garble(Manifest.load(shards).shard_paths[0])
    with caplog.at_level(logging.WARNING):
        clips = _datamodule(shards, val=str(shards), max_bad_fraction=0.3).val_clips()
    assert len(clips) == 15 and "shard-000000.tar" in caplog.text
    with pytest.raises(TooManyBadSamples, match="5 of 20 samples"):
        _datamodule(shards, val=str(shards), max_bad_fraction=0.1).val_clips()


def test_missing_shards_and_bad_settings_are_usage_errors(tmp_path):
    with pytest.raises(UsageError, match="no such directory"):
        MotionDataModule(str(tmp_path / "nope/shard-{000000..000003}.tar"))
    with pytest.raises(UsageError, match="no manifest.json"):
        MotionDataModule(str(tmp_path))
    shards = write_toy_shards(tmp_path / "s", num_clips=10, max_clips=10)
    with pytest.raises(UsageError, match="batch_size"):
        MotionDataModule(str(shards), batch_size=0)
    dm = _datamodule(shards)
    dm.trainer = SimpleNamespace(global_rank=0, world_size=2, current_epoch=0, lightning_module=None)
    with pytest.raises(UsageError, match="1 shards cannot be split disjointly across 2 ranks"):
        dm.train_dataloader()


def test_url_patterns_and_validation_set(toy_shards):
    pattern = str(toy_shards / "shard-{000000..000007}.tar")
    dm = MotionDataModule(pattern, val=str(toy_shards), batch_size=8, max_len=30, min_len=10, batches_per_epoch=2,
                          num_workers=0)
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
    # what Lightning's trainer tells the datamodule
    dm.trainer = SimpleNamespace(global_rank=rank, world_size=world, current_epoch=0, lightning_module=None)
    base = dm.train_dataloader()
    loader = StreamLoader(base.dataset, num_workers=2, collate_fn=base.collate_fn, multiprocessing_context=start_method)
    ids = [i for batch in loader for i in batch["id"]]
    gathered = [None] * world
    dist.all_gather_object(gathered, {"rank": rank, "batches": len(ids) // 4, "ids": ids})
    if rank == 0:
        torch.save(gathered, out)
    dist.destroy_process_group()


def test_two_ranks_read_disjoint_shards_and_equal_batch_counts(tmp_path):
    # the rank processes start from the tests' fork server (nothing inherited from this process), their loader
    # workers are forked
    shards = write_toy_shards(tmp_path / "s", num_clips=40, max_clips=5)  # 8 shards
    out = tmp_path / "gathered.pt"
    spawn_ranks(_rank_main, (2, _free_port(), str(shards), "fork", str(out)), 2)
    r0, r1 = torch.load(out)
    assert r0["batches"] == r1["batches"] == 5

    def shard_of(clip_id):
        return int(clip_id.split(".")[1]) // 5

    assert {shard_of(i) for i in r0["ids"]} <= {0, 2, 4, 6}
    assert {shard_of(i) for i in r1["ids"]} <= {1, 3, 5, 7}
    assert not set(r0["ids"]) & set(r1["ids"])


def test_captioned_clips_are_used_whole_up_to_the_cap(toy_shards):
    from omg.evaluation import prompt_set

    lengths = {f"clip.{i:04d}": len(toy_clip(i)) for i in range(40)}  # 20..79 frames
    dm = _datamodule(toy_shards, clips="whole", max_len=60, min_len=10)
    for batch in _epoch(dm.train_dataloader()):
        for clip_id, n in zip(batch["id"], batch["lengths"].tolist()):
            assert n == min(lengths[clip_id], 60)
    # the evaluation's real motions: the clip its caption describes
    from omg.data.loaders import ClipDataset

    samples = ClipDataset.from_shards(dm.train_urls, dm.feature_dim, dm.windows).samples
    prompts = prompt_set(samples, 40, seed=0, windows=dm.windows)
    for text, n in zip(prompts.texts, prompts.lengths.tolist()):
        assert n == min(lengths[f"clip.{int(text.split()[1]):04d}"], 60)


def test_whole_clips_shorter_than_min_len_are_not_trained_on(toy_shards):
    """min_len filters whole clips, in the stream and in memory (the papers' length filters: the toy
    clips have 20..79 frames); a set with no clip that long is one line, not an endless loop."""
    from omg.data.loaders import in_memory_loader

    lengths = {f"clip.{i:04d}": len(toy_clip(i)) for i in range(40)}
    dm = _datamodule(toy_shards, clips="whole", max_len=60, min_len=50, batches_per_epoch=20)
    seen = [(clip_id, n) for batch in _epoch(dm.train_dataloader())
            for clip_id, n in zip(batch["id"], batch["lengths"].tolist())]
    assert {lengths[c] >= 50 for c, _ in seen} == {True} and len({c for c, _ in seen}) > 5
    assert all(n == min(lengths[c], 60) for c, n in seen)
    memory = in_memory_loader(dm.train_urls, dm.feature_dim, dm.windows, 4, 0, dm.collate)
    assert {lengths[s["meta"]["id"]] >= 50 for s in memory.dataset.samples} == {True}
    with pytest.raises(UsageError, match="data.min_len=80: no clip of the shards"):
        _epoch(_datamodule(toy_shards, clips="whole", max_len=90, min_len=80).train_dataloader())


def test_batch_composition_draws_every_clip_however_short(tmp_path):
    """`omg shards inspect`'s batch report draws as training does, but from every clip (no min_len)."""
    from helpers import JointPositions
    from omg.data.shards import ShardWriter
    from omg.skeleton import SMPL22
    from omg.tools.shards import batch_composition

    ShardWriter(tmp_path, JointPositions(SMPL22), fps=20.0, max_clips=5, log=lambda m: None).write(
        toy_clip(i, frames=12) for i in range(10))
    assert "captions" in batch_composition(tmp_path, batch_size=4, shuffle_buffer=8, batches=5)


def test_clips_auto_follows_what_the_model_asks_for(toy_shards):
    """``clips: auto`` cuts what ``clip_sampling`` says, which `omg fit` links from the model's class when it parses
    the config (the data module never reads the trainer's model back: an attached one changes nothing)."""
    from helpers import REPO
    from helpers.configs import parse
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.evaluator import EvaluatorModule
    from omg.lit.pretrain import PretrainModule

    dm = _datamodule(toy_shards)  # clips: auto
    assert dm.windows.mode == "windows"  # no model named: sliding windows
    dm.trainer = SimpleNamespace(global_rank=0, world_size=1, current_epoch=0,
                                 lightning_module=SimpleNamespace(clip_sampling="whole"))
    assert dm.windows.mode == "windows"
    assert _datamodule(toy_shards, clip_sampling="whole").windows.mode == "whole"
    assert _datamodule(toy_shards, clips="windows", clip_sampling="whole").windows.mode == "windows"
    assert PretrainModule.clip_sampling == "windows"
    assert ControlNetModule.clip_sampling == EvaluatorModule.clip_sampling == "whole"
    for config, mode in (("pretrain", "windows"), ("controlnet", "whole"), ("omgpt", "whole")):
        assert parse(REPO / f"configs/mini/{config}.yaml").data.clip_sampling == mode, config
    with pytest.raises(UsageError, match="data.clips"):
        _datamodule(toy_shards, clips="crops")
    with pytest.raises(UsageError, match="data.clip_sampling"):
        _datamodule(toy_shards, clip_sampling="auto")


def test_window_starts_follow_the_sliding_window_distribution():
    from scipy.stats import chisquare

    T, low, high, n = 50, 10, 30, 100_000
    w, rng = WindowSampler(max_len=high, min_len=low), np.random.default_rng(0)
    starts = np.bincount([w.random(T, rng)[0] for _ in range(n)], minlength=T)
    # l ~ U[low, high], then start ~ U[0, T - l]
    expected = np.zeros(T)
    for length in range(low, high + 1):
        expected[: T - length + 1] += 1 / (high - low + 1) / (T - length + 1)
    assert starts[: T - low + 1].min() > 0 and starts[T - low + 1:].sum() == 0  # every possible start occurs
    assert chisquare(starts[: T - low + 1], expected[: T - low + 1] * n).pvalue > 1e-3


def test_long_clips_contribute_in_proportion_to_their_frames(tmp_path):
    from helpers import JointPositions
    from omg.data.shards import ShardWriter
    from omg.skeleton import SMPL22

    clips = [toy_clip(i, frames=40 if i % 2 else 160) for i in range(40)]  # 20 short, 20 four times longer
    ShardWriter(tmp_path / "s", JointPositions(SMPL22), fps=20.0, max_clips=5, log=lambda m: None).write(clips)
    dm = _datamodule(tmp_path / "s", batches_per_epoch=400, max_len=40, min_len=20, shuffle_buffer=16)
    ids = [i for b in _epoch(dm.train_dataloader()) for i in b["id"]]
    long_share = sum(int(i.split(".")[1]) % 2 == 0 for i in ids) / len(ids)
    assert abs(long_share - 0.8) < 0.04, long_share  # 160 / (160 + 40) of the frames


def test_windows_default_to_the_papers_one_frame_minimum(toy_shards):
    """Without data.min_len a window is l ~ U[1, L] (OMG Sec. 3.1: "even a single keyframe"); a whole captioned
    clip still needs HumanML3D's 40 frames."""
    assert WindowSampler().min_len == 1 and WindowSampler(mode="whole").min_len == 40
    dm = MotionDataModule(str(toy_shards), num_workers=0)
    assert dm.windows.mode == "windows" and dm.windows.min_len == 1, "OMG Sec. 3.1: l ~ U[1, L]"
    assert WindowSampler(max_len=20, mode="whole").min_len == 20  # a cap below 40 is the floor
    assert MotionDataModule(str(toy_shards), num_workers=0, clip_sampling="whole").windows.min_len == 40
    with pytest.raises(UsageError, match="min_len"):
        _datamodule(toy_shards, min_len=0)


@pytest.mark.parametrize("size", ["base", "large", "huge", "giant"])
def test_pretraining_configs_draw_window_lengths_uniformly_from_1_to_300(toy_shards, size):
    """configs/pretrain_{size}.yaml as `omg fit` parses it: l ~ U[1, 300] (OMG Sec. 3.1), each length about
    equally often, 1 frame included."""
    from scipy.stats import chisquare

    from helpers import REPO
    from helpers.configs import parse
    from omg.data.paired import PairedDataModule

    data = parse(REPO / f"configs/pretrain_{size}.yaml").data.as_dict()
    dm = PairedDataModule(**{**data, "train": str(toy_shards), "val": None, "num_workers": 0})  # omg fit's data
    w, rng = dm.windows, np.random.default_rng(0)
    assert (w.mode, w.min_len, w.max_len) == ("windows", 1, 300), f"{size}: OMG Sec. 3.1 draws l ~ U[1, L = 300]"
    lengths = np.array([w.random(1000, rng)[1] for _ in range(30_000)])
    assert lengths.min() == 1 and lengths.max() == 300, (lengths.min(), lengths.max())
    assert chisquare(np.bincount(lengths, minlength=301)[1:]).pvalue > 1e-3
