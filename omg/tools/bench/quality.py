"""``omg bench quality``: FID and R-precision against sampling steps and seconds per motion."""

from __future__ import annotations

import time
from pathlib import Path

from omg.errors import UsageError
from omg.tools.args import NonNegativeInt, PositiveInt


def bench_quality(
    ckpt: Path,
    evaluator: str,
    val: str,
    samplers: tuple[str, ...] = ("ddim", "dpmpp"),
    steps: tuple[PositiveInt, ...] = (5, 10, 20, 50, 100, 200),
    replications: PositiveInt = 3,
    num_prompts: PositiveInt = 64,
    max_len: PositiveInt = 196,
    batch_size: PositiveInt = 64,
    seed: NonNegativeInt = 0,
    out: Path = Path("out/quality"),
    command: str = "omg bench quality",
    prompts: str | None = None,
    samples_per_prompt: PositiveInt = 4,
) -> list[dict]:
    """FID and R-precision against sampling steps and seconds per motion, for each sampler: the
    evaluation protocol of ``omg test`` (seeded prompt sets from the validation shards, a frozen
    evaluator, mean ± 95% CI over replications) at every (sampler, steps). Writes quality.csv and
    quality.png into ``out`` and names, per sampler, the fewest steps whose FID lies within the
    95% CI of 200-step DDIM (the paper's setting).

    Args:
        ckpt: a text-conditioned checkpoint (ControlNet)
        evaluator: the evaluator checkpoint (as EvalCallback.evaluator)
        val: the validation shard directory the prompts and real motions come from
        samplers: registered samplers to compare, a list such as [ddim, dpmpp]
        steps: sampling step counts, a list such as [10, 20, 200]
        replications: prompt sets and seeds per setting (mean ± 95% CI over them)
        num_prompts: prompts per replication
        max_len: longest clip, in frames (longer clips are cropped)
        batch_size: motions sampled at once
        seed: the protocol's seed
        out: folder for quality.csv and quality.png
        command: the command line, recorded with the results
        prompts: also score prompt following (``omg.metrics.following``) on a prompt file with
            targets: ``following`` (the built-in set) or a YAML path; adds the following columns
        samples_per_prompt: generations of each prompt of the prompt file per replication

    Returns:
        One row per (sampler, steps): seconds per motion and each metric's mean and CI.
    """
    import csv

    from omg.data.datamodule import MotionDataModule
    from omg.evaluation import (
        build_evaluator,
        check_evaluator_spec,
        evaluate,
        file_prompt_set,
        parse_metrics,
        prompt_set,
        summarize,
    )
    from omg.files import check_output_dir
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import MotionDiffusionModule
    from omg.lit.sampling import SamplingSettings
    from omg.metrics.following import CATEGORIES, load_prompts
    from omg.registry import SAMPLERS

    for name in samplers:
        SAMPLERS.get(name)
    out = check_output_dir(out)
    module = load_module(ckpt, expect=MotionDiffusionModule).eval()
    if not module.text_conditional:
        raise UsageError(f"--ckpt {ckpt}: the quality curve needs a text-conditioned (ControlNet) checkpoint")
    data = MotionDataModule(val=val, max_len=max_len, clips="whole")
    samples, windows = data.val_clips().samples, data.windows
    model = build_evaluator(evaluator, key="--evaluator")
    check_evaluator_spec(model, data.spec, key="--evaluator")
    metrics = parse_metrics(["fid", {"r_precision": {"pool_size": min(32, num_prompts)}}])
    following = None
    if prompts is not None:
        entries = load_prompts(None if prompts == "following" else prompts)
        following = file_prompt_set(entries, samples_per_prompt, data.spec.fps, max_len)
    rows = []
    for name in samplers:
        for n in steps:
            seconds, motions = 0.0, 0

            def generate(texts, lengths, batch_seed, name=name, n=n):
                nonlocal seconds, motions
                start = time.perf_counter()
                motion = module.sample(list(texts), lengths, SamplingSettings(steps=n, sampler=name, seed=batch_seed,
                                                                                 use_ema=False))
                seconds, motions = seconds + time.perf_counter() - start, motions + len(texts)
                return motion

            runs = [evaluate(generate, model, prompt_set(samples, num_prompts, seed + r, windows), metrics, seed=seed,
                             replication=r, spec=data.spec) for r in range(replications)]
            summary = summarize(runs)
            row = {"sampler": name, "steps": n, "s_per_motion": seconds / motions}
            keys = ["fid", "r_precision/top1", "r_precision/top3"]
            if following is not None:
                summary |= summarize([evaluate(generate, None, following, {"following": {}}, seed=seed, replication=r,
                                               spec=data.spec) for r in range(replications)])
                keys += [k for k in ("following", *(f"following/{c}" for c in CATEGORIES)) if k in summary]
            for key in keys:
                row[f"{key}_mean"], row[f"{key}_ci95"] = summary[key]["mean"], summary[key]["ci95"]
            rows.append(row)
            extra = f" {row['following_mean']:.3f} ± {row['following_ci95']:.3f} |" if following is not None else ""
            print(f"| {name} | {n} | {row['s_per_motion']:.3f} | {row['fid_mean']:.3f} ± {row['fid_ci95']:.3f} "
                  f"| {row['r_precision/top3_mean']:.3f} ± {row['r_precision/top3_ci95']:.3f} |{extra}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "quality.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_quality(rows, out / "quality.png", command)
    reference = next((r for r in rows if r["sampler"] == "ddim" and r["steps"] == 200), None)
    if reference is not None:
        for name in samplers:
            within = [r["steps"] for r in rows if r["sampler"] == name
                      and abs(r["fid_mean"] - reference["fid_mean"]) <= reference["fid_ci95"]]
            print(f"{name}: fewest steps with FID within the 95% CI of 200-step DDIM "
                  f"({reference['fid_mean']:.3f} ± {reference['fid_ci95']:.3f}): {min(within) if within else 'none'}")
    print(f"wrote {out / 'quality.csv'} and {out / 'quality.png'}  (`{command}`)")
    return rows


def plot_quality(rows: list[dict], path: Path, command: str) -> None:
    """FID and R-precision top-3 against steps and against seconds per motion, one line per sampler."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from omg.files import atomic_path

    fig, axes = plt.subplots(2, 2, figsize=(10, 7))
    for name in dict.fromkeys(r["sampler"] for r in rows):
        mine = [r for r in rows if r["sampler"] == name]
        for row_axes, key in zip(axes, ("fid", "r_precision/top3")):
            for ax, x in zip(row_axes, ("steps", "s_per_motion")):
                ax.errorbar([r[x] for r in mine], [r[f"{key}_mean"] for r in mine],
                            yerr=[r[f"{key}_ci95"] for r in mine], marker="o", capsize=3, label=name)
                ax.set_xscale("log")
                ax.set_xlabel("sampling steps" if x == "steps" else "seconds per motion")
                ax.set_ylabel(key.replace("/", " "))
                ax.grid(True, alpha=0.3)
    axes[0][0].legend()
    fig.suptitle("\n".join(textwrap.wrap(command, 160)), fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
