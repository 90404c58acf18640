"""``omg bench control``: spatial control measured on held-out real takes: control error, foot skating and cost."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from omg.tools.args import ClosedUnitInterval, FiniteFloat, NonNegativeInt, PositiveInt


def bench_control(
    ckpt: Path,
    val: str,
    takes: PositiveInt = 16,
    max_len: PositiveInt = 120,
    steps: PositiveInt = 50,
    sampler: str = "ddim",
    keyframe_every: float = 2.0,
    wrist: str = "right_wrist",
    batch_size: PositiveInt = 16,
    iterations: NonNegativeInt | None = None,
    final_iterations: NonNegativeInt | None = None,
    smooth: float | None = None,
    curvature: ClosedUnitInterval | None = None,
    smoothing: FiniteFloat | None = None,
    contacts: bool = True,
    ground: bool = False,
    inpaint: bool = True,
    evaluator: str | None = None,
    seed: NonNegativeInt = 0,
    command: str = "omg bench control",
) -> dict:
    """Each held-out take's own root path (every frame), its full-body keyframes every ``keyframe_every``
    seconds and one wrist's positions (every frame) as constraints; the checkpoint samples every take (from its
    caption when text-conditioned) with and without them at the same settings. Prints a Markdown table: control
    error at the constrained joints and frames (mean and max cm, share within 5 and 10 cm), the root path's
    mean error, foot skating of both and of the real takes, seconds per motion of both, and with an evaluator
    FID and R-precision (top 3) of both against the real takes (realism kept under control).

    Args:
        ckpt: an OMG checkpoint (the ControlNet, or the pretrained prior)
        val: the held-out shard directory (the small recipe's shards/bandai1/val, or a user's own)
        takes: held-out takes to constrain (the first ones of a seeded order)
        max_len: longest take, in frames (longer takes are cropped)
        steps: sampling steps
        sampler: a registered sampler
        keyframe_every: seconds between full-body keyframes (from 0)
        wrist: the joint whose positions are constrained at every frame
        batch_size: motions sampled at once
        iterations, final_iterations, smooth, curvature: the steering's (``omg.lit.control.Control``; default its
            own)
        smoothing: frames of the Gaussian every denoised estimate is smoothed over time by (sampling's smoothing,
            ``omg.lit.control.smoothed``; 0: off; default: the checkpoint's), with and without the constraints
        contacts: keep still the feet the model's own contact channels plant (``"contacts": "model"``)
        ground: keep still the feet each estimate puts on the ground, low and slow (``"contacts": "ground"``)
        inpaint: write in the features a target states outright (the steering's ``inpaint``; --no_inpaint: the
            solve alone moves them)
        evaluator: an evaluator checkpoint (as ``omg bench quality --evaluator``): adds FID and R-precision; the
            R-precision pool is every take (at most 32)
        seed: the prompt order's and the noise's seed
        command: the command line, recorded with the results
    """
    from omg.data.datamodule import MotionDataModule
    from omg.evaluation import build_evaluator, check_evaluator_spec, evaluate, parse_metrics, prompt_set
    from omg.lit.checkpoint import load_module
    from omg.lit.control import Control, distances
    from omg.lit.pretrain import MotionDiffusionModule
    from omg.lit.sampling import SamplingSettings, check_smoothing
    from omg.metrics.joints import FootSkating
    from omg.motion import length_mask
    from omg.tools.bench.timeline import joint_jerk

    if smoothing is not None:
        check_smoothing(smoothing, "--smoothing")
    module = load_module(ckpt, expect=MotionDiffusionModule).eval()
    data = MotionDataModule(val=val, max_len=max_len, clips="whole")
    judge = None
    if evaluator is not None:
        judge = build_evaluator(evaluator, key="--evaluator")
        check_evaluator_spec(judge, data.spec, key="--evaluator")
    chosen = prompt_set(data.val_clips().samples, takes, seed, data.windows)
    rep, skeleton, fps = module.representation, module.representation.skeleton, module.spec.fps
    hand = skeleton.index(wrist)

    def jerk_of(joints: torch.Tensor) -> float:  # (N, T, J, 3) -> the mean of each take's joint jerk on its frames
        return float(sum(joint_jerk(j[:n], fps).mean() for j, n in zip(joints, chosen.lengths.tolist())) / len(joints))
    real = rep.decode(chosen.motions)  # (N, T, J, 3) the takes in the model's world
    mask = length_mask(chosen.lengths, real.shape[1])  # (N, T)
    N, T, J = real.shape[:3]
    weights = torch.zeros(N, T, J)
    axes = torch.zeros(N, T, J, 3, dtype=torch.bool)
    groups = torch.full((N, T, J), -1)
    every = max(round(keyframe_every * fps), 1)
    keyframes = torch.zeros(T, dtype=torch.bool)
    keyframes[::every] = True
    weights[:, keyframes] = 1.0
    axes[:, keyframes] = True
    groups[:, keyframes] = 0
    weights[:, :, hand], axes[:, :, hand], groups[:, :, hand] = 1.0, True, 1
    weights[:, :, 0], axes[:, :, 0, 0], axes[:, :, 0, 2], groups[:, :, 0] = 1.0, True, True, 2
    weights, groups = weights * mask[..., None], torch.where(mask[..., None], groups, -1)
    steering = {k: v for k, v in (("iterations", iterations), ("final_iterations", final_iterations),
                                  ("smooth", smooth), ("curvature", curvature)) if v is not None}
    control = Control(targets=real, axes=axes, weights=weights, tolerance=torch.zeros(N, T, J), groups=groups,
                      names=("keyframes", wrist, "path"), own_contacts=contacts, ground_contacts=ground, fps=fps,
                      inpaint=inpaint, **steering)
    texts = chosen.texts if module.text_conditional else None
    results: dict[str, dict] = {}
    for name, given in (("unconstrained", None), ("constrained", control)):
        seconds, motions = 0.0, []
        for start in range(0, N, batch_size):
            rows = slice(start, min(start + batch_size, N))
            part = None if given is None else _rows(given, rows, int(chosen.lengths[rows].max()))
            began = time.perf_counter()
            motion = module.sample(None if texts is None else list(texts[rows]), chosen.lengths[rows],
                                   SamplingSettings(steps=steps, sampler=sampler, seed=seed + start, use_ema=False,
                                                    control=part, smoothing=smoothing))
            seconds += time.perf_counter() - began
            motions.append(torch.nn.functional.pad(motion, (0, 0, 0, T - motion.shape[1])))
        features = torch.cat(motions)
        joints = rep.decode(features)
        skating = FootSkating(skeleton, fps)
        skating.update(joints, mask)
        dist = distances(joints, control)[weights > 0] * 100  # cm at every constrained joint and frame
        path = (joints[:, :, 0, [0, 2]] - real[:, :, 0, [0, 2]]).norm(dim=-1)[mask] * 100
        results[name] = {"mean_cm": float(dist.mean()), "max_cm": float(dist.max()), "jerk": jerk_of(joints),
                         "within_5cm": float((dist <= 5).double().mean()),
                         "within_10cm": float((dist <= 10).double().mean()), "path_cm": float(path.mean()),
                         "foot_skating": float(skating.compute()), "s_per_motion": seconds / N}
        if judge is not None:  # the same motions, scored against the same takes
            scores = evaluate(_replay(features), judge, chosen,
                              parse_metrics(["fid", {"r_precision": {"pool_size": min(32, N)}}]), seed=seed,
                              spec=data.spec)
            results[name] |= {"fid": scores["fid"], "r_precision_top3": scores["r_precision/top3"],
                              "real_r_precision_top3": scores.get("real/r_precision/top3", float("nan"))}
    real_skating = FootSkating(skeleton, fps)
    real_skating.update(real, mask)
    real_jerk = jerk_of(real)
    reads = getattr(module, "hints", None) is not None and module.hints.enabled  # a ControlNet trained with hints
    print(f"`{command}`: {N} held-out takes of {val}, {steps} {sampler} steps, keyframes every {keyframe_every:g} s, "
          f"{wrist} and the root path at every frame{', planted feet kept still' if contacts else ''}"
          f"{', feet on the ground kept still' if ground else ''}{'' if inpaint else ', no inpainting'}"
          f"{', read by the network (hints)' if reads else ''}; real takes' "
          f"foot skating {float(real_skating.compute()):.3f}, joint jerk {real_jerk:.1f} m/s³")
    realism = " FID | R-precision top 3 |" if judge is not None else ""
    print("| sampling | mean cm | max cm | within 5 cm | within 10 cm | path cm | foot skating | jerk m/s³ |"
          f"{realism} s / motion |")
    print("|---|---|---|---|---|---|---|---|" + "---|" * (3 if judge is not None else 1))
    for name, r in results.items():
        scored = f" {r['fid']:.3f} | {r['r_precision_top3']:.3f} |" if judge is not None else ""
        print(f"| {name} | {r['mean_cm']:.2f} | {r['max_cm']:.2f} | {r['within_5cm']:.3f} | {r['within_10cm']:.3f} "
              f"| {r['path_cm']:.2f} | {r['foot_skating']:.3f} | {r['jerk']:.1f} |{scored} {r['s_per_motion']:.2f} |",
              flush=True)
    free, steered = results["unconstrained"], results["constrained"]
    skating = steered["foot_skating"] / max(free["foot_skating"], 1e-9)
    fid = f"FID {steered['fid'] / max(free['fid'], 1e-9):.2f}x, " if judge is not None else ""
    real = f"; real takes' R-precision top 3 {free['real_r_precision_top3']:.3f}" if judge is not None else ""
    print(f"constrained / unconstrained: {fid}foot skating {skating:.2f}x, cost "
          f"{steered['s_per_motion'] / free['s_per_motion']:.2f}x{real}")
    return results


def _replay(features):
    """evaluate's ``generate`` handing back motions already sampled, in order: with one rank its batches are
    contiguous slices of the prompt set, from the first."""
    position = 0

    def generate(texts, lengths, seed):
        nonlocal position
        rows = features[position:position + len(texts)]
        position += len(texts)
        return rows

    return generate


def _rows(control, rows: slice, frames: int):
    """The ``Control`` of some motions of a batch of per-motion controls, over their first ``frames`` frames (a
    batch is sampled at its own longest take's length)."""
    from dataclasses import replace

    def cut(x):
        return None if x is None else x[rows, :frames]

    return replace(control, targets=cut(control.targets), axes=cut(control.axes), weights=cut(control.weights),
                   tolerance=cut(control.tolerance), groups=cut(control.groups), contacts=cut(control.contacts),
                   facing=cut(control.facing))
