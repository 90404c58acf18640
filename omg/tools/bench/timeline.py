"""``omg bench timeline``: prompt timelines and body-part composition on held-out captions, scored by the
objective prompt-following check (``omg.metrics.following``), with the smoothness of each transition and the
cost against plain sampling."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from omg.errors import UsageError
from omg.tools.args import FiniteFloat, NonNegativeInt, NonNegativeSeconds, PositiveFiniteFloat, PositiveInt

HAND, BODY = ("hand",), ("turn", "travel", "pace")  # the kinds of target an arm part / the legs and root answer for


def joint_jerk(joints, fps: float):
    """(T, J, 3) metres -> (T - 3,) the mean over joints of |d³x/dt³| (m/s³), frame t at the middle of its window."""
    import torch

    jerk = torch.diff(torch.as_tensor(joints, dtype=torch.float64), n=3, dim=0) * fps ** 3  # (T-3, J, 3)
    return jerk.norm(dim=-1).mean(-1)


def mean(values) -> float:
    """The mean of ``values``, NaN for none (a run that samples no timeline)."""
    return float(np.mean(values)) if len(values) else float("nan")


def held_out_captions(samples: list[dict], label: str, prompts: Path | None) -> list[tuple[str, list[dict], str]]:
    """(caption, targets, action label) of every held-out clip caption whose action label has targets under the
    prompt file's ``labels:`` (``omg.metrics.following.label_targets``), each caption once."""
    from omg.metrics.following import label_targets

    table, seen, out = label_targets(prompts), set(), []
    for s in samples:
        action = str((s["meta"].get("labels") or {}).get(label))
        for text in s["texts"]:
            if action in table and text not in seen:
                seen.add(text)
                out.append((text, table[action], action))
    return out


def bench_timeline(
    ckpt: Path,
    val: str,
    segments: tuple[PositiveInt, ...] = (2, 3),
    timelines: PositiveInt = 6,
    segment_seconds: PositiveFiniteFloat = 3.0,
    transition: PositiveFiniteFloat = 0.5,
    context: NonNegativeSeconds | None = None,
    chains: str = "joint",
    coupling: FiniteFloat | None = None,
    compositions: NonNegativeInt = 4,
    composition_seconds: PositiveFiniteFloat = 4.0,
    samples: PositiveInt = 4,
    steps: PositiveInt = 50,
    sampler: str = "ddim",
    guidance: FiniteFloat | None = None,
    smoothing: FiniteFloat | None = None,
    seed: NonNegativeInt = 0,
    prompts: Path | None = None,
    label: str = "content",
    only_timelines: tuple[PositiveInt, ...] = (),
    only_compositions: tuple[PositiveInt, ...] = (),
    command: str = "omg bench timeline",
) -> dict:
    """Prompt timelines and body-part composition of a text-conditioned OMG checkpoint on the held-out captions
    of ``val`` (the clips whose ``label`` has targets in the prompt file's ``labels:``):

    - timelines of two or three captions (``segments``), ``segment_seconds`` each, meeting with a ``transition``
      crossing: each segment scored by the prompt-following check on its own frames, against the same caption
      generated alone at the segment's length with the same seeds (the issue's target: at least 0.9x its rate);
    - transition smoothness: the joints' mean jerk within ``transition`` of each boundary, against the real
      held-out takes' mean jerk (target: at most 1.5x), and the same model's jerk sampling one caption alone;
    - body-part compositions: a locomotion caption on the legs and root, a hand caption on the arms, each scored
      on its own targets (locomotion: turn, travel, pace; hands: hand), both parts passing counted (target: 0.7),
      against the two captions joined as one plain sentence;
    - cost: sampling seconds per second of motion against plain sampling (one caption, the same settings).

    Prints Markdown tables and returns the figures.

    Args:
        ckpt: a text-conditioned OMG checkpoint (ControlNet)
        val: the held-out shard directory the captions and the real takes come from (a user's own with the same
            command)
        segments: segments per timeline, a list such as [2, 3], taken in turn
        timelines: timelines to make (each of different captions, neighbours of different actions)
        segment_seconds: seconds per segment
        transition: seconds two segments cross over in (the timeline file's transition)
        context: seconds each text's denoiser sees on either side of its own frames (the timeline file's
            context; default: the whole motion)
        chains: how the texts are sampled (the timeline file's chains): joint (one chain, the texts'
            estimates blended) or separate (one chain per text)
        coupling: with separate chains, each chain's pull towards the composed estimate, 0..1 (the timeline
            file's coupling; default: its default)
        compositions: body-part compositions to make
        composition_seconds: seconds per composition
        samples: motions per timeline, composition and caption alone (seeds seed..seed+samples-1)
        steps: sampling steps
        sampler: a registered sampler
        guidance: the guidance scale (default: the checkpoint's)
        smoothing: frames of the Gaussian every denoised estimate is smoothed over time by (sampling's
            smoothing, ``omg.lit.control.smoothed``; 0: off; default: the checkpoint's), for every motion the
            bench samples
        seed: the seed of the choice of captions and of the first motion
        prompts: the prompt file whose ``labels:`` give the targets (default: the built-in set)
        label: the clip label that names the action (a Bandai-Namco take's ``content``)
        only_timelines: sample only these timelines, numbered 1.. as the full run makes them (the same
            captions and seeds; the others are chosen, not sampled): a list such as [2, 4]
        only_compositions: sample only these compositions, numbered the same way (either list given, the
            kind it does not name is not sampled)
        command: the command line, printed with the results
    """
    import torch

    from omg.data.datamodule import MotionDataModule
    from omg.generation.timeline import check_chains, parse_timeline
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import MotionDiffusionModule
    from omg.lit.sampling import SamplingSettings, check_smoothing
    from omg.metrics.following import Joints, check_target, passes
    from omg.metrics.joints import FootSkating
    from omg.motion import get_representation
    from omg.registry import SAMPLERS

    SAMPLERS.get(sampler)
    if smoothing is not None:
        check_smoothing(smoothing, "--smoothing")
    check_chains(chains, "--chains")
    if coupling is not None and (not 0 <= coupling <= 1 or chains != "separate"):
        raise UsageError(f"--coupling {coupling:g}: a number in [0, 1], with --chains separate")
    how = {"context": context, "chains": chains, **({} if coupling is None else {"coupling": coupling})}
    for name, picked, made in (("only_timelines", only_timelines, timelines),
                               ("only_compositions", only_compositions, compositions)):
        if past := [n for n in picked if n > made]:
            raise UsageError(f"--{name}: {past[0]} is past the {made} the run makes (--{name.split('_')[1]})")
    module = load_module(ckpt, expect=MotionDiffusionModule).eval()
    if not module.text_conditional:
        raise UsageError(f"--ckpt {ckpt}: a timeline needs a text-conditioned (ControlNet) checkpoint")
    data = MotionDataModule(val=val, max_len=100_000, clips="whole")
    held_out = data.val_clips().samples
    captions = held_out_captions(held_out, label, prompts)
    if len({a for _, _, a in captions}) < 2:
        raise UsageError(f"--val {val}: fewer than two actions with targets among its captions ({label!r} labels)")
    fps, rep, at = module.spec.fps, module.representation, Joints(module.spec.skeleton)
    seeds = tuple(range(seed, seed + samples))
    rng = np.random.default_rng(seed)
    clock = {"timeline": [0.0, 0], "plain": [0.0, 0], "parts": [0.0, 0]}

    def sample(texts, frames: int, spans=None, what: str = "plain") -> torch.Tensor:
        """``samples`` motions (n, T, J, 3) of ``texts`` (one per motion) or of a timeline, timed under ``what``."""
        timeline = None if spans is None else spans.resolve(frames, fps, rep)
        settings = SamplingSettings(steps=steps, sampler=sampler, guidance=guidance, seeds=seeds, use_ema=False,
                                    timeline=timeline, smoothing=smoothing)
        start = time.perf_counter()
        features = module.sample(None if spans is not None else list(texts), [frames] * samples, settings)
        clock[what][0] += time.perf_counter() - start
        clock[what][1] += samples * frames / fps  # seconds of motion: timelines are longer than one caption alone
        return rep.decode(features.float())

    def score(joints: torch.Tensor, targets: list[dict], kinds: tuple[str, ...] | None = None) -> list[bool]:
        chosen = [t for t in targets if kinds is None or check_target(t) in kinds]
        return [all(passes(j, t, fps, at) for t in chosen) for j in joints]

    # -- timelines ---------------------------------------------------------------------------------------------
    by_action: dict[str, list] = {}
    for c in captions:
        by_action.setdefault(c[2], []).append(c)
    made, segment_rows, boundary_jerk, alone_jerk = [], [], [], []
    seg_frames = round(segment_seconds * fps)
    for i in range(timelines):
        k = segments[i % len(segments)]
        actions = list(rng.permutation(sorted(by_action)))
        chosen = []
        for action in actions:
            if len(chosen) == k:
                break
            pool = by_action[action]
            chosen.append(pool[int(rng.integers(len(pool)))])
        while len(chosen) < k:  # fewer actions than segments: repeat, never next to itself
            chosen.append(chosen[-2])
        if (only_timelines or only_compositions) and i + 1 not in only_timelines:
            continue
        spans = parse_timeline({"timeline": [{"start": j * segment_seconds, "end": (j + 1) * segment_seconds,
                                              "text": c[0]} for j, c in enumerate(chosen)], "transition": transition,
                                **how})
        frames = round(k * segment_seconds * fps)
        joints = sample(None, frames, spans, "timeline")  # (n, T, J, 3)
        made.append([c[0] for c in chosen])
        for j, (text, targets, action) in enumerate(chosen):
            own = joints[:, j * seg_frames:(j + 1) * seg_frames]
            segment_rows.append({"timeline": i + 1, "text": text, "targets": targets, "passed": score(own, targets)})
        for j in range(1, k):
            b, w = j * seg_frames, max(2, round(transition * fps))
            for m in joints:
                boundary_jerk.append(float(joint_jerk(m[max(0, b - w - 3): b + w], fps).mean()))
    alone: dict[str, list[bool]] = {}
    for text, targets in {r["text"]: r["targets"] for r in segment_rows}.items():
        joints = sample([text] * samples, seg_frames)
        alone[text] = score(joints, targets)
        alone_jerk += [float(joint_jerk(m, fps).mean()) for m in joints]
    real = get_representation(data.spec.representation, data.spec.skeleton)
    real_jerk = [float(joint_jerk(real.decode(torch.as_tensor(s["motion"]).float()), data.spec.fps).mean())
                 for s in held_out if len(s["motion"]) > 4]
    in_timeline = mean([np.mean(r["passed"]) for r in segment_rows])
    by_itself = mean([np.mean(alone[r["text"]]) for r in segment_rows])

    # -- body-part compositions ---------------------------------------------------------------------------------
    def moves(targets: list[dict]) -> bool:  # a locomotion caption: it goes somewhere, and not by its hands
        return (any(check_target(t) in ("turn", "travel") or t.get("pace") in ("walk", "run") for t in targets)
                and not any(check_target(t) in HAND for t in targets))

    walkers = [c for c in captions if moves(c[1])]
    wavers = [c for c in captions if any(check_target(t) in HAND for t in c[1])]
    comp_rows = []
    comp_frames = round(composition_seconds * fps)
    for i in range(compositions if walkers and wavers else 0):
        walk, wave = walkers[int(rng.integers(len(walkers)))], wavers[int(rng.integers(len(wavers)))]
        hands = {t.get("hand") for t in wave[1] if check_target(t) in HAND}
        arm = "arms" if hands & {"both", "either"} else f"{hands.pop()}_arm"
        if (only_timelines or only_compositions) and i + 1 not in only_compositions:
            continue
        spans = parse_timeline({"parts": [{"parts": ["legs", "root"], "text": walk[0]},
                                          {"parts": [arm], "text": wave[0]}], "transition": transition,
                                **how})
        sentence = f"{walk[0].rstrip('.')} and {wave[0].removeprefix('a person ')}"
        row = {"composition": i + 1, "walk": walk[0], "wave": wave[0], "arm": arm, "sentence": sentence}
        for key, joints in (("parts", sample(None, comp_frames, spans, "parts")),
                            ("plain", sample([sentence] * samples, comp_frames))):
            body, hand = score(joints, walk[1], BODY), score(joints, wave[1], HAND)
            skating = FootSkating(module.spec.skeleton, fps)
            skating.update(joints, torch.ones(joints.shape[:2], dtype=torch.bool))
            row[key] = {"body": body, "hand": hand, "both": [a and b for a, b in zip(body, hand)],
                        "skating": float(skating.compute())}
        comp_rows.append(row)
    if not comp_rows:
        print("(no body-part composition: the captions need a locomotion action and a hand action with targets)")

    # -- tables -------------------------------------------------------------------------------------------------
    def rate(values) -> str:
        values = list(values)
        return f"{sum(values)}/{len(values)} ({np.mean(values):.2f})" if values else "–"

    print(f"\n`{command}`")
    if segment_rows:
        print("\n| # | timeline segment | its targets | passes in the timeline | passes alone |\n"
              "|---:|---|---|---:|---:|")
    for r in segment_rows:
        targets = "; ".join(", ".join(f"{k}: {v}" for k, v in t.items()) for t in r["targets"])
        print(f"| {r['timeline']} | {r['text']} | {targets} | {rate(r['passed'])} | {rate(alone[r['text']])} |")
    ratio = in_timeline / by_itself if by_itself else float("nan")
    real_mean, boundary_mean, alone_mean = (mean(v) for v in (real_jerk, boundary_jerk, alone_jerk))
    costs = {k: v[0] / v[1] for k, v in clock.items() if v[1]}
    print("\n| measure | value | target |\n|---|---:|---:|")
    if segment_rows:
        print(f"| segments passing, in timelines / alone | {in_timeline:.3f} / {by_itself:.3f} ({ratio:.2f}x) "
              "| >= 0.9x |\n"
              f"| joint jerk at the transitions / real held-out takes (m/s³) | {boundary_mean:.1f} / {real_mean:.1f} "
              f"({boundary_mean / real_mean:.2f}x) | <= 1.5x |\n"
              f"| joint jerk of one caption alone / real (m/s³) | {alone_mean:.1f} / {real_mean:.1f} "
              f"({alone_mean / real_mean:.2f}x) | |")
    if comp_rows:
        both = [b for r in comp_rows for b in r["parts"]["both"]]
        plain = [b for r in comp_rows for b in r["plain"]["both"]]
        print(f"| body-part compositions: both parts pass / as one plain sentence | {rate(both)} / {rate(plain)} "
              "| >= 0.7 |")
        skated = [float(np.mean([r[k]["skating"] for r in comp_rows])) for k in ("parts", "plain")]
        print(f"| foot skating, compositions / the plain sentence | {skated[0]:.3f} / {skated[1]:.3f} "
              f"({skated[0] / max(skated[1], 1e-9):.2f}x) | |")
    for what in ("timeline", "parts"):
        if what in costs and "plain" in costs:
            print(f"| sampling seconds per second of motion, {what} / plain ({steps} {sampler} steps) | "
                  f"{costs[what]:.3f} / {costs['plain']:.3f} ({costs[what] / costs['plain']:.2f}x) | <= 3x |")
    if comp_rows:
        print("\n| # | composition: legs and root / arm | arm part | locomotion passes | hand passes | both | plain "
              "sentence: both |\n|---:|---|---|---:|---:|---:|---:|")
        for r in comp_rows:
            p = r["parts"]
            print(f"| {r['composition']} | {r['walk']} / {r['wave']} | {r['arm']} | {rate(p['body'])} | "
                  f"{rate(p['hand'])} | {rate(p['both'])} | {rate(r['plain']['both'])} |")
    return {"segments": segment_rows, "alone": alone, "timelines": made, "in_timeline": in_timeline,
            "alone_rate": by_itself, "jerk": {"boundary": boundary_mean, "real": real_mean, "alone": alone_mean},
            "compositions": comp_rows, "seconds_per_motion_second": costs}
