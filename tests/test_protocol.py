"""The evaluation protocol runner: prompt sets, one pass, mean ± 95% CI over replications, reports."""

from __future__ import annotations

import json
import math

import pytest
import torch

from helpers import REPO
from omg.data.datamodule import MotionDataModule
from omg.data.loaders import ClipDataset
from omg.errors import UsageError
from omg.evaluation import (
    EvalSettings,
    _my_batches,
    evaluate,
    markdown_table,
    parse_metrics,
    prompt_set,
    protocol,
    summarize,
    write_report,
)
from omg.models.evaluator import TextMotionEvaluator

MINI = REPO / "shards/mini/human263"


@pytest.fixture(scope="session")
def setup():
    data = MotionDataModule(str(MINI / "train"), val=str(MINI / "val"), max_len=40, min_len=30, num_workers=0)
    samples = ClipDataset.from_shards(data.val_urls, data.feature_dim, data.windows).samples
    torch.manual_seed(0)
    evaluator = TextMotionEvaluator(data.spec, text_encoder="hash", config="mini").eval()  # untrained is enough here
    return data, samples, evaluator


def test_summary_is_mean_and_t2m_confidence_interval():
    runs = [{"fid": 1.0, "r": 0.5}, {"fid": 2.0, "r": 0.5}, {"fid": 3.0, "r": 0.5}, {"fid": 4.0, "r": 0.5}]
    s = summarize(runs)
    # np.std (population) of 1..4 = sqrt(1.25); CI = 1.96 · std / sqrt(4)
    assert s["fid"]["mean"] == 2.5 and s["fid"]["std"] == pytest.approx(math.sqrt(1.25))
    assert s["fid"]["ci95"] == pytest.approx(1.96 * 1.1180339887 / 2) and s["fid"]["values"] == [1, 2, 3, 4]
    assert s["r"] == {"mean": 0.5, "std": 0.0, "ci95": 0.0, "values": [0.5] * 4}
    seen = []
    out = protocol(lambda r: seen.append(r) or {"x": float(r)}, 3)
    assert seen == [0, 1, 2] and out["x"]["mean"] == 1.0
    with pytest.raises(UsageError, match="replications"):
        protocol(lambda r: {}, 0)


def test_reports_are_written_as_json_and_markdown(tmp_path):
    summary = summarize([{"fid": 1.0}, {"fid": 3.0}])
    json_path, md_path = write_report(tmp_path / "run", summary, {"replications": 2, "seed": 0, "metrics": {"fid": {}}})
    saved = json.loads(json_path.read_text())
    assert saved["settings"]["seed"] == 0 and saved["metrics"]["fid"]["mean"] == 2.0
    assert "| fid | 2.0000 | ±1.3859 |" in md_path.read_text()  # std 1, 1.96 / √2
    assert markdown_table(summary, 2).splitlines()[0].startswith("| metric | mean | ±95% CI (2 replications)")
    assert not list((tmp_path / "run").glob(".*tmp*"))  # atomic writes leave no temporaries


def test_prompt_sets_are_seeded_and_cover_small_sets(setup):
    data, samples, _ = setup
    a, b = prompt_set(samples, 25, 3, data.windows), prompt_set(samples, 25, 3, data.windows)
    assert a.texts == b.texts and torch.equal(a.motions, b.motions) and len(a) == 25
    assert a.texts != prompt_set(samples, 25, 4, data.windows).texts
    assert all(30 <= n <= 40 for n in a.lengths.tolist()) and a.motions.shape[1] == int(a.lengths.max())
    for i, n in enumerate(a.lengths.tolist()):  # un-normalised real features, zero beyond each length
        assert a.motions[i, n:].abs().sum() == 0 and a.motions[i, :n].abs().sum() > 0
    clips_used = {t for t in a.texts}
    assert len(clips_used) > len(samples)  # 25 prompts from 10 clips: clips repeat with other captions


def test_bad_metric_configs_name_the_key():
    assert parse_metrics(["fid", {"diversity": {"num_pairs": 5}}]) == {"fid": {}, "diversity": {"num_pairs": 5}}
    assert list(parse_metrics(None)) == ["fid", "r_precision", "mm_dist", "diversity", "multimodality"]
    for spec, message in ((["fdi"], "metrics: unknown metric 'fdi'; known metrics:"),
                          (["mpjpe"], "metrics: mpjpe cannot be computed"),
                          (["fid_ood"], "metrics: fid_ood cannot be computed"),
                          ([{"fid": {}, "mm_dist": {}}], "metrics: each entry")):
        with pytest.raises(UsageError, match=message):
            parse_metrics(spec)


def test_batches_split_contiguously_across_ranks():
    whole = _my_batches(10, 3, 0, 1)
    assert whole == [(0, 0, 3), (1, 3, 6), (2, 6, 9), (3, 9, 10)]
    assert _my_batches(10, 3, 0, 2) + _my_batches(10, 3, 1, 2) == whole


def test_one_pass_is_deterministic_and_a_perfect_generator_matches_the_data(setup):
    data, samples, evaluator = setup
    prompts = prompt_set(samples, 24, 0, data.windows)
    metrics = parse_metrics(["fid", {"r_precision": {"pool_size": 8}}, "mm_dist", {"diversity": {"num_pairs": 10}},
                             {"multimodality": {"num_pairs": 2}}, "foot_skating", "intra_fid", "clip_score"])
    settings = EvalSettings(batch_size=10, mm_prompts=3, mm_repeats=3)

    def noisy(texts, lengths, seed):  # a "model": seeded noise around the mean pose
        gen = torch.Generator().manual_seed(seed)
        return torch.tensor(data.manifest.mean) + 0.1 * torch.randn(len(texts), int(lengths.max()), 263, generator=gen)

    def run(seed):
        return evaluate(noisy, evaluator, prompts, metrics, seed=seed, settings=settings, spec=data.spec)

    first = run(0)
    assert first == run(0) and first != run(1)
    assert {"fid", "r_precision/top3", "mm_dist", "diversity", "multimodality", "foot_skating", "intra_fid/human",
            "real/diversity", "real/foot_skating", "real/r_precision/top1"} <= set(first)
    assert first["fid"] > 0 and first["multimodality"] > 0

    batches = iter([prompts.slice(s, e).motions for _, s, e in _my_batches(len(prompts), 10, 0, 1)])
    perfect = evaluate(lambda texts, lengths, seed: next(batches), evaluator, prompts, parse_metrics(
        ["fid", {"r_precision": {"pool_size": 8}}, "mm_dist", {"diversity": {"num_pairs": 10}}, "foot_skating"]),
        seed=0, settings=settings, spec=data.spec)
    assert perfect["fid"] == pytest.approx(0, abs=1e-6)
    for key in ("r_precision/top1", "mm_dist", "diversity", "foot_skating"):
        assert perfect[key] == pytest.approx(perfect[f"real/{key}"])
