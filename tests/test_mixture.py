"""Weighted mixtures of shard sets: proportions, exact resume, pooled statistics, bad sets, inspect."""

from __future__ import annotations

import dataclasses
import json
import logging

import numpy as np
import pytest
import yaml
from scipy.stats import binomtest

from helpers import TINY_DIT, JointPositions, toy_clip, walking_clip
from omg.data.datamodule import MotionDataModule
from omg.data.shards import FeatureStats, ShardWriter
from omg.errors import UsageError
from omg.registry import REPRESENTATIONS
from omg.skeleton import SMPL22


@pytest.fixture(autouse=True)
def _toy_representation(monkeypatch):
    """The toy representation by name, as pooled statistics look a set's representation up."""
    REPRESENTATIONS.names()  # the built-ins first
    monkeypatch.setitem(REPRESENTATIONS._entries, JointPositions.name, JointPositions)


def toy_set(out, prefix: str, num_clips: int, shift: float = 0.0, fps: float = 20.0, max_clips: int = 5):
    """A set whose clip ids start with ``prefix`` and whose joints are raised by ``shift`` metres."""
    clips = []
    for i in range(num_clips):
        clip = toy_clip(i)
        positions = clip.positions.copy()
        positions[..., 1] += shift
        clips.append(dataclasses.replace(clip, id=f"{prefix}.{i:04d}", positions=positions, fps=fps))
    ShardWriter(out, JointPositions(SMPL22), fps=fps, max_clips=max_clips, log=lambda m: None).write(clips)
    return out


def features(clips) -> np.ndarray:
    return np.concatenate([c.positions.reshape(len(c), -1) for c in clips]).astype(np.float64)


@pytest.fixture(scope="session")
def two_sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("mix")
    with pytest.MonkeyPatch.context() as mp:
        REPRESENTATIONS.names()
        mp.setitem(REPRESENTATIONS._entries, JointPositions.name, JointPositions)
        return toy_set(root / "a", "a", 40), toy_set(root / "b", "b", 20, shift=1.0)


def _dm(train, **kw):
    defaults = dict(batch_size=16, max_len=30, min_len=10, batches_per_epoch=6, num_workers=0, shuffle_buffer=16)
    return MotionDataModule(train, **{**defaults, **kw})


def _weighted(a, b, wa=0.8, wb=0.2):
    return [{"path": str(a), "weight": wa}, {"path": str(b), "weight": wb}]


def test_samples_follow_the_weights(two_sets):
    a, b = two_sets
    loader = _dm(_weighted(a, b), batches_per_epoch=200).train_dataloader()
    batches = list(loader)
    sets = np.concatenate([bt["shard_set"].numpy() for bt in batches])
    ids = [i for bt in batches for i in bt["id"]]
    assert [i[0] for i in ids] == ["ab"[k] for k in sets]  # each sample is tagged with its own set
    n, from_a = len(ids), int((sets == 0).sum())
    assert n == 3200 and binomtest(from_a, n, 0.8).pvalue > 1e-3, from_a / n
    assert binomtest(from_a, n, 0.7).pvalue < 1e-6  # the test can tell 0.8 from 0.7
    assert loader.state_dict()["mixture"] == {"sets": [str(a), str(b)], "shares": [0.8, 0.2],
                                              "drawn": [from_a, n - from_a]}


def test_the_mixture_is_deterministic_per_seed_and_rank(two_sets):
    from types import SimpleNamespace

    def ids(seed, rank=0):
        dm = _dm(_weighted(*two_sets), seed=seed)
        dm.trainer = SimpleNamespace(global_rank=rank, world_size=2, current_epoch=0, lightning_module=None)
        return [i for bt in dm.train_dataloader() for i in bt["id"]]

    assert ids(1) == ids(1) and ids(1) != ids(2)
    shard = {i: int(i.split(".")[1]) // 5 for i in ids(1) + ids(1, rank=1)}
    assert {shard[i] % 2 for i in ids(1)} == {0} and {shard[i] % 2 for i in ids(1, rank=1)} == {1}  # every set split


@pytest.mark.parametrize("num_workers", [0, 2])
def test_a_resumed_mixture_continues_exactly(two_sets, num_workers):
    loader = _dm(_weighted(*two_sets), num_workers=num_workers).train_dataloader()
    list(loader)
    full = list(loader)  # epoch 1
    partial = _dm(_weighted(*two_sets), num_workers=num_workers).train_dataloader()
    first = _dm(_weighted(*two_sets), num_workers=num_workers).train_dataloader()
    first.load_state_dict({"epoch": 1, "batches_done": 0})
    head = [bt for _, bt in zip(range(4), first)]
    saved = first.state_dict()
    assert saved["epoch"] == 1 and saved["batches_done"] == 4
    assert sum(saved["mixture"]["drawn"]) == 4 * 16
    partial.load_state_dict(saved)
    rest = list(partial)
    assert [bt["id"] for bt in head + rest] == [bt["id"] for bt in full]
    assert [bt["lengths"].tolist() for bt in rest] == [bt["lengths"].tolist() for bt in full[4:]]
    assert partial.state_dict() == loader.state_dict()  # the same position, per-set counts included


def test_a_changed_mixture_warns_on_resume(two_sets, caplog):
    a, b = two_sets
    state = _dm(_weighted(a, b)).train_dataloader().state_dict()
    state = {**state, "epoch": 0, "batches_done": 2, "mixture": {"sets": [str(a), str(b)], "shares": [0.5, 0.5],
                                                                  "drawn": [16, 16]}}
    loader = _dm(_weighted(a, b)).train_dataloader()
    with caplog.at_level(logging.WARNING):
        loader.load_state_dict(state)
    assert "not the mixture the checkpoint was trained on" in caplog.text and "50.0%" in caplog.text
    assert len(list(loader)) == 4  # it goes on from the saved position


def _direct_stats(parts: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray]:
    """mean and std of frames drawn from each part with its share, computed from the frames."""
    mean = sum(share * x.mean(0) for x, share in parts)
    second = sum(share * (x * x).mean(0) for x, share in parts)
    return mean, np.sqrt(np.maximum(second - mean * mean, 0))


def test_pooled_stats_of_an_unweighted_list_are_those_of_the_concatenated_clips(two_sets):
    a, b = two_sets
    dm = _dm([str(a), str(b)])
    clips = [toy_clip(i) for i in range(40)] + [toy_clip(i) for i in range(20)]
    x = features(clips)
    x[len(features(clips[:40])):, 1::3] += 1.0  # set b's joints are raised by a metre
    mean, std = x.mean(0), x.std(0)
    np.testing.assert_allclose(dm.spec.mean, mean, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dm.spec.std, std, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(dm.mixture.shares, [len(x[: len(features(clips[:40]))]) / len(x),
                                                   1 - len(features(clips[:40])) / len(x)])
    # the first set's statistics (what a list of sets was normalised with before) are far off
    assert np.abs(np.asarray(dm.spec.mean) - MotionDataModule(str(a)).spec.mean).max() > 0.1
    # batches are normalised with the pooled statistics
    batch = next(iter(dm.train_dataloader()))
    n = int(batch["lengths"][0])
    raw = batch["motion"][0, :n].numpy() * np.asarray(dm.spec.std) + np.asarray(dm.spec.mean)
    assert abs(raw[:, 0].mean() - (int(batch["id"][0].split(".")[1]))) < 0.1  # x of joint 0 is the clip index


def test_pooled_stats_of_a_weighted_mixture_weight_each_sets_frames_by_its_share(two_sets):
    a, b = two_sets
    dm = _dm(_weighted(a, b, 3.0, 1.0))  # shares 0.75, 0.25: neither the clip nor the frame proportion
    xa = features([toy_clip(i) for i in range(40)])
    xb = features([toy_clip(i) for i in range(20)])
    xb[:, 1::3] += 1.0
    mean, std = _direct_stats([(xa, 0.75), (xb, 0.25)])
    np.testing.assert_allclose(dm.spec.mean, mean, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dm.spec.std, std, rtol=1e-4, atol=1e-5)
    concatenated = np.concatenate([xa, xb])
    assert np.abs(np.asarray(dm.spec.mean) - concatenated.mean(0)).max() > 0.01  # the weights matter


def test_pooled_stats_are_finalized_once_by_the_representation(tmp_path):
    """humanml3d263 averages its std per feature group: the groups must be averaged over the pooled
    std, not the sets' finalized ones."""
    from omg.motion import get_representation

    rep = get_representation("humanml3d263", SMPL22)
    clips = {"a": [walking_clip(i) for i in range(6)], "b": [walking_clip(50 + i) for i in range(3)]}
    for name, cs in clips.items():
        ShardWriter(tmp_path / name, rep, 20.0, max_clips=4, log=lambda m: None).write(cs)
    dm = _dm([str(tmp_path / "a"), str(tmp_path / "b")], batches_per_epoch=1)
    stats = FeatureStats()
    for clip in clips["a"] + clips["b"]:
        stats.add(rep.encode(clip)[0])
    mean, std = rep.finalize_stats(*stats.mean_std())
    np.testing.assert_allclose(dm.spec.mean, mean, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(dm.spec.std, std, rtol=1e-4, atol=1e-6)


def test_old_manifests_without_sums_pool_from_mean_std_or_say_why_not(two_sets, tmp_path):
    import shutil

    a, b = two_sets
    old = tmp_path / "old_b"
    shutil.copytree(b, old)
    manifest = json.loads((old / "manifest.json").read_text())
    del manifest["sums"]
    (old / "manifest.json").write_text(json.dumps(manifest))
    with_sums, without = _dm(_weighted(a, b)).spec, _dm(_weighted(a, old)).spec
    np.testing.assert_allclose(without.mean, with_sums.mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(without.std, with_sums.std, rtol=1e-4, atol=1e-6)
    manifest["stats_origin"] = "source"  # a published mean/std: its raw moments are unknown
    (old / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(UsageError, match=f"shard set {old}: its manifest has no 'sums'.*rebuild it") as e:
        _dm(_weighted(a, old))
    assert "\n" not in str(e.value)
    _dm(str(old))  # alone, a set keeps its own mean/std


def test_sets_that_disagree_are_one_line_errors_naming_the_set_and_the_field(two_sets, tmp_path):
    a, _ = two_sets
    fast = toy_set(tmp_path / "fast", "f", 5, fps=30.0)
    with pytest.raises(UsageError) as e:
        _dm([{"path": str(a), "weight": 1}, {"path": str(fast), "weight": 1}])
    message = str(e.value)
    assert "\n" not in message and f"data.train[1] ({fast})" in message and "fps 20.0 vs 30.0" in message
    from omg.motion import get_representation

    other = tmp_path / "h263"
    ShardWriter(other, get_representation("humanml3d263", SMPL22), 20.0, log=lambda m: None).write([walking_clip(0)])
    with pytest.raises(UsageError, match=r"data.train\[1\] .*representation test-positions vs humanml3d263"):
        _dm([str(a), str(other)])


@pytest.mark.parametrize("train, error", [
    ([{"path": "A", "weight": 0}], "'weight' must be a positive number"),
    ([{"path": "A", "weight": "heavy"}], "'weight' must be a positive number"),
    ([{"path": "A", "wieght": 1}], "unknown key 'wieght'"),
    ([{"weight": 1}], "'path' must name"),
    ([{"path": "A", "weight": 1}, "B"], "/b has no weight; give every set a weight, or none"),
    ([{"path": "A", "weight": 1}, {"path": "A", "weight": 2}], "listed twice"),
    ([3], "expected a directory or URL"),
])
def test_bad_mixture_entries_are_one_line_errors(two_sets, train, error):
    a, b = two_sets
    train = json.loads(json.dumps(train).replace('"A"', json.dumps(str(a))).replace('"B"', json.dumps(str(b))))
    with pytest.raises(UsageError, match=error) as e:
        _dm(train)
    assert "\n" not in str(e.value)


def test_each_set_must_split_across_the_ranks(two_sets, tmp_path):
    from types import SimpleNamespace

    a, _ = two_sets
    small = toy_set(tmp_path / "small", "s", 5)  # one shard
    dm = _dm(_weighted(a, small))
    dm.trainer = SimpleNamespace(global_rank=0, world_size=2, current_epoch=0, lightning_module=None)
    with pytest.raises(UsageError, match=f"1 shards of {small} cannot be split disjointly across 2 ranks"):
        dm.train_dataloader()


def test_inspect_prints_each_sets_share_from_a_config_or_the_list(two_sets, tmp_path, capsys):
    from omg.tools.shards import shards_inspect

    a, b = two_sets
    config = tmp_path / "mixture.yaml"
    config.write_text(yaml.safe_dump({"data": {"train": _weighted(a, b, 0.5, 0.5)}}))
    shards_inspect([str(config)])
    out = capsys.readouterr().out
    frames = {name: json.loads((d / "manifest.json").read_text())["num_frames"] for name, d in (("a", a), ("b", b))}
    share_of_frames = frames["a"] / (frames["a"] + frames["b"])
    line_a = next(line for line in out.splitlines() if line.startswith(f"{a}: 40 clips"))
    assert f"{frames['a']} frames" in line_a and "weight 0.5, share 50.0% of samples" in line_a
    assert f"({0.5 / share_of_frames:.2f}x its share of the frames)" in line_a
    assert f"{b}: 20 clips" in out and "mixture: 2 sets, 60 clips" in out
    assert "8 of 8 shards verified" in out and "4 of 4 shards verified" in out  # each set is validated as before
    shards_inspect([yaml.safe_dump(_weighted(a, b), default_flow_style=True).strip()])
    assert "share 80.0% of samples" in capsys.readouterr().out


def _fit_mixture(h263_shards, root, kill_at=None, resume=False):
    import lightning as L

    from helpers.resume import Recorder, run_until_killed
    from omg.lit.pretrain import PretrainModule

    L.seed_everything(0, verbose=False)
    data = _dm([{"path": str(h263_shards / "train"), "weight": 0.7}, {"path": str(h263_shards / "val"), "weight": 0.3}],
               batch_size=4, batches_per_epoch=4, shuffle_buffer=8)
    model = PretrainModule(flavor="mini", dit=TINY_DIT,
                           ema_decay=0.9, spec=data.spec, optim={"lr": 1e-3, "warmup_steps": 2})
    recorder = Recorder()
    run_until_killed(model, data, root, max_steps=7, kill_at=kill_at, resume=resume, callbacks=[recorder])
    return recorder.steps


def test_a_killed_run_on_a_mixture_resumes_its_stream_exactly(h263_shards, tmp_path):
    from helpers.resume import assert_identical, final_state

    steps = _fit_mixture(h263_shards, tmp_path / "full")
    first = _fit_mixture(h263_shards, tmp_path / "killed", kill_at=5)
    second = _fit_mixture(h263_shards, tmp_path / "killed", resume=True)
    assert min(second) == 5 and {**first, **second} == steps
    expected, resumed = final_state(tmp_path / "full"), final_state(tmp_path / "killed")
    assert_identical(resumed, expected)
    (position,) = expected["data"]
    assert position["epoch"] == 1 and position["batches_done"] == 3 and sum(position["mixture"]["drawn"]) == 12
