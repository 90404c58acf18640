"""Evaluation metrics against direct numpy/scipy computations, batch-split and 2-rank DDP invariance."""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest
import scipy.linalg
import torch
import torch.distributed as dist
from scipy.ndimage import uniform_filter1d

from helpers.forked import spawn_ranks
from omg.metrics import (
    FID,
    FIDOOD,
    MPJPE,
    CLIPScore,
    Diversity,
    FootSkating,
    IntraFID,
    MMDist,
    MultiModality,
    OneNNA,
    RPrecision,
)
from omg.registry import METRICS

# ---------------------------------------------------------------------------------------------
# references: the formulas as the HumanML3D / GMD evaluation scripts write them


def fid_reference(real: np.ndarray, gen: np.ndarray) -> float:
    mu1, mu2 = real.mean(0), gen.mean(0)
    s1, s2 = np.cov(real, rowvar=False), np.cov(gen, rowvar=False)
    covmean = scipy.linalg.sqrtm(s1 @ s2).real
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def r_precision_reference(text: np.ndarray, motion: np.ndarray, pool: int, seed: int, top_k: int = 3) -> list:
    order = torch.randperm(len(text), generator=torch.Generator().manual_seed(seed)).numpy()
    order = order[: len(text) // pool * pool]
    hits = np.zeros(top_k)
    for start in range(0, len(order), pool):
        idx = order[start : start + pool]
        dist = np.linalg.norm(text[idx, None] - motion[None, idx], axis=-1)
        ranked = np.argsort(dist, axis=1)
        correct = ranked == np.arange(pool)[:, None]
        hits += np.cumsum(correct[:, :top_k], axis=1).sum(0)
    return list(hits / len(order))


def skating_reference(joints: np.ndarray, feet: list[int], fps: float = 20.0) -> np.ndarray:
    """GMD's calculate_skating_ratio, per clip, on (B, T, J, 3) with all frames valid."""
    verts = joints[:, :, feet].transpose(0, 2, 3, 1)  # (B, K, 3, T)
    vel = np.linalg.norm(verts[:, :, [0, 2], 1:] - verts[:, :, [0, 2], :-1], axis=2) * fps
    vel_avg = uniform_filter1d(vel, axis=-1, size=5, mode="constant", origin=0)
    height = verts[:, :, 1]
    contact = (height[:, :, :-1] < 0.05) & (height[:, :, 1:] < 0.05)
    skating = contact & (vel > 0.5) & (vel_avg > 0.5)
    return skating.any(1).sum(1) / skating.shape[-1]


def gaussian(rng, n: int, f: int, shift: float = 0.0, rank: int | None = None) -> np.ndarray:
    mix = rng.standard_normal((rank or f, f))
    return rng.standard_normal((n, rank or f)) @ mix + shift


def t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(x)


# ---------------------------------------------------------------------------------------------
# feature-distribution metrics


def test_registered_names():
    expected = {"fid", "fid_ood", "intra_fid", "one_nna", "r_precision", "mm_dist", "clip_score", "diversity",
                "multimodality", "mpjpe", "foot_skating"}
    assert expected <= set(METRICS.names())
    assert METRICS.get("fid") is FID and METRICS.get("fid_ood") is FIDOOD
    assert METRICS.build("foot_skating", skeleton="smal35").feet == [10, 20, 14, 24]  # all four paws


@pytest.mark.parametrize("rank", [None, 5], ids=["full-rank", "rank-deficient"])
def test_fid_matches_scipy_sqrtm(rank):
    rng = np.random.default_rng(0)
    real, gen = gaussian(rng, 300, 24, rank=rank), gaussian(rng, 200, 24, shift=0.7, rank=rank)
    metric = FID(num_features=24)
    metric.update(t(real), real=True)
    metric.update(t(gen).float(), real=False)
    assert metric.compute().item() == pytest.approx(fid_reference(real, gen.astype(np.float32)), rel=1e-6)


def test_fid_of_a_set_with_itself_is_zero_and_ood_is_fid():
    x = t(gaussian(np.random.default_rng(1), 100, 8, rank=3))
    for cls in (FID, FIDOOD):
        metric = cls(num_features=8)
        metric.update(x, real=True)
        metric.update(x, real=False)
        assert metric.compute().item() == pytest.approx(0.0, abs=1e-6)


def test_fid_asks_for_enough_samples_and_the_right_width():
    metric = FID(num_features=4)
    with pytest.raises(ValueError, match=r"shape \(N, 4\)"):
        metric.update(torch.zeros(3, 5), real=True)
    metric.update(torch.randn(5, 4), real=True)
    metric.update(torch.randn(1, 4), real=False)
    with pytest.raises(ValueError, match="at least 2 real and 2 generated samples, got 5 and 1"):
        metric.compute()


def test_intra_fid_is_the_mean_of_per_category_fids():
    rng = np.random.default_rng(2)
    categories = ["dog", "horse", "cat"]
    real = [gaussian(rng, 80, 6, shift=c) for c in range(3)]
    gen = [gaussian(rng, 60, 6, shift=c + 0.5) for c in range(2)]  # no generated cats
    metric = IntraFID(num_features=6, categories=categories)
    for c, x in enumerate(real):
        metric.update(t(x), torch.full((len(x),), c), real=True)
    mixed = np.concatenate(gen)
    metric.update(t(mixed), torch.tensor([0] * 60 + [1] * 60), real=False)
    out = metric.compute()
    per = [fid_reference(real[c], gen[c]) for c in range(2)]
    assert out["intra_fid/dog"].item() == pytest.approx(per[0], rel=1e-6)
    assert out["intra_fid/horse"].item() == pytest.approx(per[1], rel=1e-6)
    assert out["intra_fid/cat"].isnan()
    assert out["intra_fid"].item() == pytest.approx(np.mean(per), rel=1e-6)
    with pytest.raises(ValueError, match="labels must lie in 0..2"):
        metric.update(t(mixed[:2]), torch.tensor([0, 3]), real=True)


def one_nna_reference(real: np.ndarray, gen: np.ndarray) -> float:
    x = np.concatenate([real, gen])
    label = np.arange(len(x)) < len(real)
    dist = np.linalg.norm(x[:, None] - x[None], axis=-1)
    np.fill_diagonal(dist, np.inf)
    return float((label[dist.argmin(1)] == label).mean())


def test_one_nna():
    rng = np.random.default_rng(3)
    real, same, far = rng.standard_normal((3, 400, 4))
    far += 50.0

    def score(gen, chunk_size=1024):
        metric = OneNNA(chunk_size=chunk_size)
        metric.update(t(real), real=True)
        metric.update(t(gen), real=False)
        return metric.compute().item()

    assert score(far) == 1.0
    assert score(same) == pytest.approx(0.5, abs=0.06)
    assert score(same, chunk_size=7) == pytest.approx(one_nna_reference(real, same), abs=1e-12)


# ---------------------------------------------------------------------------------------------
# text–motion agreement


def test_r_precision_perfect_match_and_chance():
    rng = np.random.default_rng(4)
    x = t(rng.standard_normal((32 * 8 + 5, 16)))
    perfect = RPrecision()
    perfect.update(x, x)
    assert all(v.item() == 1.0 for v in perfect.compute().values())

    n = 32 * 300
    chance = RPrecision()
    chance.update(t(rng.standard_normal((n, 8))), t(rng.standard_normal((n, 8))))
    out = chance.compute()
    assert list(out) == ["r_precision/top1", "r_precision/top2", "r_precision/top3"]
    for k in (1, 2, 3):  # binomial std of a top-k rate over 9600 texts is below 0.003
        assert out[f"r_precision/top{k}"].item() == pytest.approx(k / 32, abs=0.01)


def test_r_precision_matches_humanml3d_argsort_protocol():
    rng = np.random.default_rng(5)
    motion = rng.standard_normal((32 * 6 + 17, 12))
    text = motion + 1.2 * rng.standard_normal(motion.shape)  # partly matched: every rank occurs
    metric = RPrecision(seed=7)
    metric.update(t(text), t(motion))
    got = [v.item() for v in metric.compute().values()]
    assert got == pytest.approx(r_precision_reference(text, motion, 32, seed=7), abs=1e-12)
    with pytest.raises(ValueError, match="at least pool_size=32 samples, got 31"):
        small = RPrecision()
        small.update(t(text[:31]), t(motion[:31]))
        small.compute()


def test_mm_dist_and_clip_score():
    rng = np.random.default_rng(6)
    text, motion = rng.standard_normal((50, 8)), rng.standard_normal((50, 8))
    mm, clip = MMDist(), CLIPScore()
    mm.update(t(text), t(motion))
    clip.update(t(text), t(motion))
    cosine = (text * motion).sum(1) / np.linalg.norm(text, axis=1) / np.linalg.norm(motion, axis=1)
    assert mm.compute().item() == pytest.approx(np.linalg.norm(text - motion, axis=1).mean(), rel=1e-12)
    assert clip.compute().item() == pytest.approx(cosine.mean(), rel=1e-12)
    same = CLIPScore()
    same.update(t(text), t(3 * text))
    assert same.compute().item() == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------
# diversity


def test_diversity_uses_seeded_pairs_over_the_whole_set():
    x = np.random.default_rng(7).standard_normal((500, 8))
    metric = Diversity(num_pairs=300, seed=3)
    metric.update(t(x))
    g = torch.Generator().manual_seed(3)
    first, second = torch.randperm(500, generator=g)[:300].numpy(), torch.randperm(500, generator=g)[:300].numpy()
    assert metric.compute().item() == pytest.approx(np.linalg.norm(x[first] - x[second], axis=1).mean(), rel=1e-12)
    few = Diversity()
    few.update(t(x[:100]))
    with pytest.raises(ValueError, match="num_pairs=300 samples, got 100"):
        few.compute()


def test_multimodality_groups_by_text():
    rng = np.random.default_rng(8)
    repeats, texts = 12, 5
    x = (rng.standard_normal((texts, repeats, 6)) * np.arange(1, texts + 1)[:, None, None]).reshape(-1, 6)
    ids = np.repeat(np.arange(texts) * 10, repeats)  # any ids; groups are taken in ascending order
    shuffle = rng.permutation(len(x))  # a text's generations need not be adjacent
    x, ids = x[shuffle], ids[shuffle]
    metric = MultiModality(num_pairs=10, seed=1)
    metric.update(t(x), t(ids))
    metric.update(t(rng.standard_normal((1, 6))), torch.tensor([999]))  # a lone generation: no pairs
    g = torch.Generator().manual_seed(1)
    expected = []
    for k in range(texts):
        group = x[ids == k * 10]
        first, second = torch.randperm(repeats, generator=g)[:10], torch.randperm(repeats, generator=g)[:10]
        expected.append(np.linalg.norm(group[first.numpy()] - group[second.numpy()], axis=1).mean())
    assert metric.compute().item() == pytest.approx(np.mean(expected), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# joint positions


def test_mpjpe_ignores_padded_frames():
    rng = np.random.default_rng(9)
    pred, target = rng.standard_normal((3, 10, 22, 3)), rng.standard_normal((3, 10, 22, 3))
    lengths = np.array([10, 4, 7])
    mask = np.arange(10)[None] < lengths[:, None]
    metric = MPJPE()
    metric.update(t(pred), t(target), t(mask))
    errors = [np.linalg.norm(pred[b, :n] - target[b, :n], axis=-1) for b, n in enumerate(lengths)]
    errors = np.concatenate([e.ravel() for e in errors])
    assert metric.compute().item() == pytest.approx(errors.mean(), rel=1e-12)


def planted_and_sliding(frames: int = 40) -> np.ndarray:
    """Two clips at 20 fps, every joint 1 m up except the toes. Clip 0: left toe planted on the
    floor, right toe sliding along x at 1 m/s 2 cm up for frames 0..19, then lifted to 30 cm
    still moving. Clip 1: both toes planted."""
    joints = np.zeros((2, frames, 22, 3))
    joints[..., 1] = 1.0
    joints[:, :, [10, 11], 1] = 0.0
    joints[0, :, 11, 0] = np.arange(frames) / 20.0
    joints[0, :20, 11, 1] = 0.02
    joints[0, 20:, 11, 1] = 0.3
    return joints


def test_foot_skating_on_a_planted_and_a_sliding_foot():
    joints = planted_and_sliding()
    metric = FootSkating("smpl22")
    metric.update(t(joints))
    # transitions 0..18 join two sliding frames (the first one's window average is 3/5 m/s,
    # still above 0.5); 19 -> 20 lifts the foot: 19 of 39 in clip 0, none in clip 1
    assert metric.compute().item() == pytest.approx((19 / 39 + 0) / 2)
    assert skating_reference(joints, [7, 8, 10, 11]) == pytest.approx([19 / 39, 0])

    padded = np.concatenate([joints, np.random.default_rng(0).uniform(-1, 0.04, (2, 15, 22, 3))], axis=1)
    mask = torch.arange(55)[None].expand(2, -1) < 40
    masked = FootSkating("smpl22")
    masked.update(t(padded), mask)
    assert masked.compute().item() == pytest.approx(19 / 78)


def test_foot_skating_matches_gmd_on_random_walks():
    rng = np.random.default_rng(10)
    joints = np.cumsum(rng.normal(0, 0.03, (4, 60, 22, 3)), axis=1)
    joints[..., 1] = np.abs(joints[..., 1])  # hover around the floor so contacts occur
    metric = FootSkating("smpl22", joints=(10, 11))
    metric.update(t(joints))
    reference = skating_reference(joints, [10, 11])
    assert reference.min() > 0
    assert metric.compute().item() == pytest.approx(reference.mean(), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# batching and DDP: the same data, however split, gives the same result


def cases() -> dict[str, tuple]:
    """name -> (metric factory, update calls); each call's tensors are split along dim 0."""
    rng = np.random.default_rng(11)
    real, gen = t(gaussian(rng, 240, 8)), t(gaussian(rng, 200, 8, shift=0.3))
    real_labels, gen_labels = t(rng.integers(0, 3, 240)), t(rng.integers(0, 3, 200))
    motion = t(rng.standard_normal((400, 8)))
    text = motion + t(rng.standard_normal((400, 8)))
    joints = t(np.cumsum(rng.normal(0, 0.03, (20, 30, 22, 3)), axis=1)).abs()
    mask = torch.arange(30)[None] < t(rng.integers(5, 31, (20, 1)))
    return {
        "fid": (lambda: FID(8), [(real, True), (gen, False)]),
        "intra_fid": (lambda: IntraFID(8, ["a", "b", "c"]), [(real, real_labels, True), (gen, gen_labels, False)]),
        "one_nna": (OneNNA, [(real, True), (gen, False)]),
        "r_precision": (RPrecision, [(text, motion)]),
        "mm_dist": (MMDist, [(text, motion)]),
        "clip_score": (CLIPScore, [(text, motion)]),
        "diversity": (Diversity, [(motion,)]),
        "multimodality": (MultiModality, [(motion, t(rng.integers(0, 20, 400)))]),
        "mpjpe": (MPJPE, [(joints, joints.flip(1), mask)]),
        "foot_skating": (FootSkating, [(joints, mask)]),
    }


def run_metric(factory, calls, bounds: list[tuple[float, float]]) -> dict[str, float]:
    """Update with the fraction ``bounds[i]`` of every call's tensors, piece by piece; compute."""
    metric = factory()
    for args in calls:
        n = len(args[0])
        for lo, hi in bounds:
            metric.update(*(a[int(lo * n) : int(hi * n)] if isinstance(a, torch.Tensor) else a for a in args))
    out = metric.compute()
    return {k: v.item() for k, v in out.items()} if isinstance(out, dict) else {"value": out.item()}


def single_process_results() -> dict[str, dict[str, float]]:
    return {name: run_metric(factory, calls, [(0, 1)]) for name, (factory, calls) in cases().items()}


def test_several_batches_equal_one():
    whole = single_process_results()
    for name, (factory, calls) in cases().items():
        split = run_metric(factory, calls, [(0, 0.2), (0.2, 0.55), (0.55, 1)])
        assert split == pytest.approx(whole[name], rel=1e-9, abs=1e-12), name


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


RANK_BOUNDS = [(0, 0.45), (0.45, 1)]  # uneven halves: cat states of different lengths are gathered


def _rank_main(rank: int, world: int, port: int, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    torch.set_num_threads(1)
    results = {name: run_metric(factory, calls, [RANK_BOUNDS[rank]]) for name, (factory, calls) in cases().items()}
    torch.save(results, f"{out}/rank{rank}.pt")
    dist.destroy_process_group()


def test_two_gloo_ranks_equal_one_process(tmp_path):
    spawn_ranks(_rank_main, (2, _free_port(), str(tmp_path)), 2)  # two gloo processes, forked
    whole = single_process_results()
    for rank in range(2):
        results = torch.load(tmp_path / f"rank{rank}.pt")
        for name, expected in whole.items():
            assert results[name] == pytest.approx(expected, rel=1e-9, abs=1e-12), (rank, name)


def test_label_accuracy_is_the_nearest_captions_label():
    from omg.metrics import EvalBatch, LabelAccuracy

    # three captions of two contents; motions sit next to a caption of their own content or not
    captions = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=torch.float64)
    content = ["walk", "walk", "bow"]
    text = captions[[0, 1, 2, 0, 2]]
    labels = [{"content": content[i], "style": "old"} for i in (0, 1, 2, 0, 2)]
    gen = torch.tensor([[1.0, 0.0], [0.5, 0.5], [0.0, 9.0], [0.0, 8.0], [9.0, 1.0]], dtype=torch.float64)
    metric = LabelAccuracy(label="content", labels={"content": ["bow", "walk"], "style": ["old"]})
    metric.eval_update(EvalBatch(text=text, gen=gen, real=text, labels=labels))
    out = metric.compute()
    # row 1 (walk) is nearest caption 0 (walk): a hit though not its own caption; row 3 (walk) is nearest bow
    assert out["label_accuracy"].item() == pytest.approx(3 / 5)
    assert out["label_accuracy/walk"].item() == pytest.approx(2 / 3)
    assert out["label_accuracy/bow"].item() == pytest.approx(1 / 2)
    real = LabelAccuracy(labels={"content": ["bow", "walk"]})
    real.eval_update(EvalBatch(text=text, gen=gen, real=text, labels=labels), real=True)
    assert real.compute()["label_accuracy"].item() == 1.0
    with pytest.raises(Exception, match="no clip of the evaluation set has a 'content' label"):
        LabelAccuracy(labels={})
