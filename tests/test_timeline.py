"""Prompt timelines and body-part composition (``omg.lit.timeline``, ``omg.generation.timeline``): each stretch of
frames and each body part follows its own text in one continuous motion, the file is checked in one line per error
with nothing written, and sampling without a timeline is the plain path."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest
import torch

from helpers import MINI, TINY_DIT
from helpers.checkpoints import save_module
from omg.errors import UsageError
from omg.generation.timeline import parse_timeline
from omg.lit.sampling import SamplingSettings
from omg.lit.timeline import (
    DEFAULT_COUPLING,
    PartText,
    Segment,
    Timeline,
    resolve_timeline,
    segment_weights,
    timeline_denoiser,
)
from omg.motion import get_representation, length_mask
from omg.skeleton import SMPL22, body_parts

WALK, WAVE = "a person walks forward", "a person waves the left hand"
FPS = 20.0


@pytest.fixture(scope="module")
def controlnet_ckpt(tmp_path_factory):
    """A tiny ControlNet (hash text) whose weights, the zero-initialised ones too, are random: every text gives
    its own x̂0."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("timeline")
    spec = MotionDataModule(str(MINI / "human263/train"), batch_size=4, max_len=40, min_len=20, num_workers=0,
                            clips="whole").spec
    torch.manual_seed(0)
    pretrain = PretrainModule(flavor="mini", dit=TINY_DIT, spec=spec, ema_decay=0)
    for module, name in ((pretrain, "pre.ckpt"), (None, "cn.ckpt")):
        if module is None:
            module = ControlNetModule(pretrained=str(root / "pre.ckpt"), text_encoder="hash",
                                      moc={"d_c": 16, "num_experts": 2}, spec=spec, ema_decay=0)
            with torch.no_grad():
                for p in module.controlnet.parameters():
                    p.add_(torch.randn_like(p) * 0.05)
        save_module(module, root / name)
    return {"controlnet": root / "cn.ckpt", "pretrain": root / "pre.ckpt"}


@pytest.fixture(scope="module")
def controlnet(controlnet_ckpt):
    from omg.lit.checkpoint import load_module

    return load_module(controlnet_ckpt["controlnet"]).eval()


# -- the format ----------------------------------------------------------------------------------------------------

BAD = [
    ({"timeline": []}, "no segments and no parts"),
    ([{"start": 0, "end": 2, "text": WALK}, {"start": 3, "end": 5, "text": WAVE}],
     "a gap between timeline[0] (ends at 2 s) and timeline[1] (starts at 3 s)"),
    ([{"start": 0, "end": 2, "text": WALK}, {"start": 2, "end": 2, "text": WAVE}],
     "timeline[1] has zero length (start = end = 2 s)"),
    ([{"start": 1, "end": 2, "text": WALK}], "timeline[0] starts at 1 s; the timeline starts the motion, at 0 s"),
    ([{"start": 0, "end": 3, "text": WALK}, {"start": 1, "end": 2, "text": WAVE}],
     "timeline[1] (1..2 s) lies inside timeline[0] (0..3 s)"),
    ([{"start": 0, "end": 2, "text": WALK}, {"start": 1.5, "end": 4, "text": WAVE}, {"start": 1, "end": 5,
                                                                                       "text": WALK}],
     "timeline[2] starts at 1 s, before timeline[1] (1.5 s); list the segments in time order"),
    ([{"start": 0, "end": float("nan"), "text": WALK}], "timeline[0].end must be a finite number of seconds"),
    ([{"start": 0, "end": 2, "text": ""}], "timeline[0].text must be a non-empty sentence"),
    ([{"start": 0, "end": 2, "txt": WALK}], "timeline[0]: unknown key 'txt'; a segment has start, end, text"),
    ([{"start": 0, "end": 2, "text": "a\x00b"}], "timeline[0].text holds the control character"),
    ({"parts": [{"parts": [], "text": WALK}]}, "parts[0].parts must be a non-empty list of body part names"),
    ({"timeline": [{"start": 0, "end": 2, "text": WALK}], "extra": 1}, "unknown key 'extra'"),
    ({"timeline": [{"start": 0, "end": 2, "text": WALK}], "context": -1}, "context must be a finite number of seconds"),
    ("walk", "expected a list of segments"),
]


@pytest.mark.parametrize("data,message", BAD)
def test_a_bad_file_is_one_line_before_anything_is_loaded(data, message, tmp_path, capsys):
    from omg.cli import main

    path = tmp_path / "t.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SystemExit) as e:  # no checkpoint at all: the file fails first
        main(["generate", "--ckpt", str(tmp_path / "none.ckpt"), "--timeline", str(path), "--out",
              str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(f"omg: error: --timeline {path}: ") and err.count("\n") == 1, err
    assert message in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("data,extra,message", [
    ([{"start": 0, "end": 2, "text": WALK}, {"start": 2, "end": 5, "text": WAVE}], ["--length", "4"],
     "timeline[1] ends at 5 s, after the motion's end (4 s)"),
    ([{"start": 0, "end": 2, "text": WALK}], ["--length", "3"],
     "the timeline ends at 2 s, before the motion's end (3 s): a gap"),
    ({"parts": [{"parts": ["legs", "tail"], "text": WALK}]}, [],
     "parts[0]: unknown body part 'tail'; smpl22's: root, torso, left_arm, right_arm, left_leg, right_leg, legs, "
     "arms, upper_body"),
    ({"parts": [{"parts": ["legs", "root"], "text": WALK}, {"parts": ["left_leg"], "text": WAVE, "start": 1}]}, [],
     "parts[0] and parts[1] both move left_hip at the same time"),
    ({"parts": [{"parts": ["left_arm"], "text": WAVE, "start": 7, "end": 9}]}, ["--length", "6"],
     "parts[0] ends at 9 s, after the motion's end (6 s)"),
])
def test_a_file_that_does_not_fit_the_model_is_one_line_and_nothing_written(controlnet_ckpt, data, extra, message,
                                                                            tmp_path, capsys):
    from omg.cli import main

    path = tmp_path / "t.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SystemExit) as e:
        main(["generate", "--ckpt", str(controlnet_ckpt["controlnet"]), "--timeline", str(path), *extra, "--out",
              str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(f"omg: error: --timeline: {message}"), err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


def test_prompts_and_a_timeline_together_and_models_without_one_are_one_line(controlnet_ckpt, tmp_path, capsys):
    from omg.cli import main

    path = tmp_path / "t.json"
    path.write_text(json.dumps([{"start": 0, "end": 1, "text": WALK}]))
    for args, message in (
            (["a person jumps", "--ckpt", str(controlnet_ckpt["controlnet"])],
             "give prompts, --timeline (whose segments carry their texts) or --unconditional, not prompts and "
             "--timeline"),
            (["--ckpt", str(controlnet_ckpt["pretrain"])],
             f"--timeline: {controlnet_ckpt['pretrain']} (PretrainModule) takes no prompt timeline; its card lists "
             "none")):
        with pytest.raises(SystemExit) as e:
            main(["generate", *args, "--timeline", str(path), "--out", str(tmp_path / "out")])
        assert e.value.code == 2 and capsys.readouterr().err == f"omg: error: {message}\n"
        assert not (tmp_path / "out").exists()


def test_body_parts_come_from_the_skeletons_chains_and_names():
    parts = body_parts(SMPL22)
    name = {k: [SMPL22.names[j] for j in v] for k, v in parts.items()}
    assert name["root"] == ["pelvis"] and name["left_arm"] == ["left_collar", "left_shoulder", "left_elbow",
                                                                 "left_wrist"]
    assert name["right_leg"] == ["right_hip", "right_knee", "right_ankle", "right_foot"]
    assert name["torso"] == ["spine1", "spine2", "spine3", "neck", "head"]
    every = sorted(j for k in ("root", "torso", "left_arm", "right_arm", "left_leg", "right_leg") for j in parts[k])
    assert every == list(range(22))  # each joint in exactly one part


def test_segments_cross_over_smoothly_and_share_every_frame():
    times = torch.arange(80, dtype=torch.float64) / FPS
    touching = segment_weights([Segment(0, 2, WALK), Segment(2, 4, WAVE)], times, transition=0.5)
    overlapping = segment_weights([Segment(0, 2.5, WALK), Segment(1.5, 4, WAVE)], times, transition=0.5)
    for w in (touching, overlapping):
        assert torch.allclose(w.sum(0), torch.ones(80, dtype=torch.float64))
        assert (w[0, 1:] <= w[0, :-1]).all() and (w[1, 1:] >= w[1, :-1]).all()  # one crossing, no jump back
    assert (touching[0, times <= 1.75] == 1).all() and (touching[1, times >= 2.25] == 1).all()
    assert (overlapping[0, times <= 1.5] == 1).all() and (overlapping[1, times >= 2.5] == 1).all()
    assert (overlapping[:, (times > 1.6) & (times < 2.4)] < 1).all()  # the whole overlap is blended
    assert float((touching[0, 1:] - touching[0, :-1]).abs().max()) < 0.2  # no jump at the boundary


# -- sampling ------------------------------------------------------------------------------------------------------


def _estimates(module, texts: list[str], mask, x, t):
    return module.denoiser(texts, mask, None)(x, t)


def test_each_segment_follows_its_own_text_away_from_the_crossing(controlnet):
    """The blended x̂0 is segment A's text's estimate on A's frames and B's on B's, the crossing a mix of the
    two: the same noisy motion denoised with each text alone, over the whole sequence."""
    frames, rep = 60, controlnet.representation
    timeline = resolve_timeline([Segment(0, 1.5, WALK), Segment(1.5, 3, WAVE)], [], frames, FPS, rep)
    mask = length_mask([frames, frames])
    gen = torch.Generator().manual_seed(0)
    x, t = torch.randn(2, frames, 263, generator=gen), torch.tensor([500, 900])
    with torch.no_grad():
        blended = timeline_denoiser(controlnet.denoiser, timeline, mask, None)(x, t)
        walk, wave = _estimates(controlnet, [WALK] * 2, mask, x, t), _estimates(controlnet, [WAVE] * 2, mask, x, t)
    a, b, crossing = slice(0, 25), slice(35, 60), slice(27, 33)  # the crossing: 1.25..1.75 s
    assert not torch.allclose(walk[:, a], wave[:, a], atol=1e-3)  # the texts differ
    assert torch.allclose(blended[:, a], walk[:, a], atol=1e-5)
    assert torch.allclose(blended[:, b], wave[:, b], atol=1e-5)
    mixed = blended[:, crossing]
    assert not torch.allclose(mixed, walk[:, crossing], atol=1e-4) and not torch.allclose(mixed, wave[:, crossing],
                                                                                         atol=1e-4)
    share = timeline.weights[0, crossing, :1]  # (6, 1) the walk's share there
    assert torch.allclose(mixed, share * walk[:, crossing] + (1 - share) * wave[:, crossing], atol=1e-5)


def test_each_body_part_takes_its_features_from_its_own_text(controlnet):
    """Legs and root from the walk, the left arm from the wave: each feature of the blended x̂0 is its joint's
    text's (the root's, which carry the trajectory, the walk's); the rest of the body follows the first entry."""
    frames, rep = 40, controlnet.representation
    timeline = resolve_timeline([], [PartText(("legs", "root"), WALK), PartText(("left_arm",), WAVE)], frames, FPS,
                                rep)
    mask = length_mask([frames])
    x, t = torch.randn(1, frames, 263, generator=torch.Generator().manual_seed(1)), torch.tensor([700])
    with torch.no_grad():
        blended = timeline_denoiser(controlnet.denoiser, timeline, mask, None)(x, t)
        walk, wave = _estimates(controlnet, [WALK], mask, x, t), _estimates(controlnet, [WAVE], mask, x, t)
    arm = torch.isin(torch.as_tensor(rep.channel_joints()), torch.tensor(body_parts(SMPL22)["left_arm"]))  # (D,)
    assert arm.sum() == 4 * 3 + 4 * 6 + 4 * 3  # ric, 6D rotation and velocity of its 4 joints
    assert torch.allclose(blended[..., arm], wave[..., arm], atol=1e-5)
    assert torch.allclose(blended[..., ~arm], walk[..., ~arm], atol=1e-5)
    assert not torch.allclose(walk[..., arm], wave[..., arm], atol=1e-3)
    assert list(torch.nonzero(~arm).flatten()[:4]) == [0, 1, 2, 3]  # the trajectory is the walk's


def test_with_a_context_each_text_sees_only_its_own_frames_and_that_much_around(controlnet):
    """``context``: text k's denoiser runs on its own window (its frames, widened by the context) cut out of the
    sequence, so what happens outside the window cannot change its estimate; without one it sees the whole
    sequence and does. Inside the window the estimate is that text's denoiser on the cut-out frames."""
    frames, rep = 80, controlnet.representation
    segments = [Segment(0, 2, WALK), Segment(2, 4, WAVE)]
    windowed = resolve_timeline(segments, [], frames, FPS, rep, context=0.5)
    whole = resolve_timeline(segments, [], frames, FPS, rep)
    assert windowed.windows == ((0, 55), (26, 80)) and whole.windows is None  # crossing 1.75..2.25 s, + 0.5 s
    assert torch.equal(windowed.weights, whole.weights)
    mask = length_mask([frames, frames])
    gen = torch.Generator().manual_seed(3)
    x, t = torch.randn(2, frames, 263, generator=gen), torch.tensor([400, 800])
    later = x.clone()
    later[:, 60:] = torch.randn(2, 20, 263, generator=gen)  # only the wave's frames past the walk's window
    with torch.no_grad():
        seen = timeline_denoiser(controlnet.denoiser, windowed, mask, None)
        unseen = timeline_denoiser(controlnet.denoiser, whole, mask, None)
        walk_cut = _estimates(controlnet, [WALK] * 2, length_mask([55, 55]), x[:, :55], t)
        a, b = seen(x, t), seen(later, t)
        assert torch.allclose(a[:, :35], walk_cut[:, :35], atol=1e-5)  # the walk's own frames: its cut-out estimate
        assert torch.equal(a[:, :25], b[:, :25])  # frames only the walk's window covers: blind to frames 60..79
        assert not torch.allclose(a[:, 60:], b[:, 60:], atol=1e-3)
        assert not torch.allclose(unseen(x, t)[:, :25], unseen(later, t)[:, :25], atol=1e-4)  # the whole sees them


def test_windows_hold_every_frame_of_their_text_and_parts_see_the_whole_motion(controlnet):
    rep = controlnet.representation
    three = resolve_timeline([Segment(0, 1, WALK), Segment(0.8, 2, WAVE), Segment(2, 3, "a person turns left")], [],
                             60, FPS, rep, context=0)
    assert three.windows == ((0, 23), (14, 45), (36, 60))  # crossings 0.65..1.15 s and 1.75..2.25 s
    parts = resolve_timeline([], [PartText(("legs", "root"), WALK), PartText(("left_arm",), WAVE, start=1.0)], 60,
                             FPS, rep, context=0.25)
    assert parts.windows == ((0, 60), (11, 60))  # the wave crosses in after 0.75 s, seen 0.25 s before
    with pytest.raises(ValueError, match="must hold its text's frames"):
        Timeline(three.texts, three.weights, ((0, 23), (20, 45), (36, 60)))


def test_a_part_with_a_window_holds_only_then(controlnet):
    frames = 60
    timeline = resolve_timeline([Segment(0, 3, WALK)], [PartText(("left_arm",), WAVE, start=1.0, end=2.0)], frames,
                                FPS, controlnet.representation)
    arm = torch.isin(torch.as_tensor(controlnet.representation.channel_joints()),
                     torch.tensor(body_parts(SMPL22)["left_arm"]))
    wave = timeline.weights[timeline.texts.index(WAVE)]  # (T, D)
    assert (wave[:15] == 0).all() and (wave[45:] == 0).all()  # before 0.75 s, after 2.25 s: the walk's alone
    assert (wave[25:35][:, arm] == 1).all() and (wave[:, ~arm] == 0).all()


def test_sampling_a_timeline_is_one_motion_and_without_one_the_plain_path(controlnet):
    """With a timeline the sampler draws one motion per row through the blended denoiser (every registered
    sampler, stance_root on top); without one, ``sample`` is the plain solver on the module's denoiser."""
    from omg.registry import SAMPLERS

    frames = 40
    settings = SamplingSettings(steps=3, seed=4, use_ema=False)
    plain = controlnet.sample([WALK, WALK], [frames, frames], settings)
    mask = length_mask([frames, frames])
    with torch.no_grad():
        x = SAMPLERS.get("ddim")(controlnet.diffusion, controlnet.denoiser([WALK, WALK], mask, None),
                                 (2, frames, 263), steps=3, generator=torch.Generator().manual_seed(4), device="cpu",
                                 dtype=torch.float32, mask=mask)
    assert torch.equal(plain, controlnet.denormalize(x))
    alone = resolve_timeline([Segment(0, frames / FPS, WALK)], [], frames, FPS, controlnet.representation)
    assert torch.equal(controlnet.sample(None, [frames, frames], SamplingSettings(steps=3, seed=4, use_ema=False,
                                                                                 timeline=alone)), plain)
    two = resolve_timeline([Segment(0, 1, WALK), Segment(1, 2, WAVE)], [], frames, FPS, controlnet.representation)
    cut = resolve_timeline([Segment(0, 1, WALK), Segment(1, 2, WAVE)], [], frames, FPS, controlnet.representation,
                           context=0.25)
    for sampler in SAMPLERS.names():
        for timeline in (two, cut):
            motion = controlnet.sample(None, [frames, frames - 6], SamplingSettings(
                steps=3, sampler=sampler, use_ema=False, timeline=timeline, stance_root=0.5))
            assert motion.shape == (2, frames, 263) and torch.isfinite(motion).all()
    with pytest.raises(ValueError, match="a timeline carries its own texts"):
        controlnet.sample([WALK], [frames], SamplingSettings(steps=1, timeline=two))


def test_a_timeline_is_sampled_step_by_step_as_every_sampler_reports_it(controlnet):
    """The blended denoiser runs the K texts in one model call a step: each registered sampler still reports its
    own steps, in order, ending at ``steps``, and watching it changes no number."""
    from omg.registry import SAMPLERS

    frames = 40
    two = resolve_timeline([Segment(0, 1, WALK), Segment(1, 2, WAVE)], [], frames, FPS, controlnet.representation)
    for sampler in SAMPLERS.names():
        settings = SamplingSettings(steps=3, sampler=sampler, use_ema=False, timeline=two, stance_root=0.5, seed=2)
        heard = []
        watched = controlnet.sample(None, [frames, frames], settings, progress=lambda *step: heard.append(step))
        assert heard == [(1, 3), (2, 3), (3, 3)], sampler
        assert torch.equal(watched, controlnet.sample(None, [frames, frames], settings)), sampler


def test_omg_generate_follows_a_timeline_file(controlnet_ckpt, tmp_path):
    from omg.cli import main
    from omg.generation.registry import generator_for
    from omg.lit.checkpoint import load_module

    path = tmp_path / "t.json"
    path.write_text(json.dumps({"timeline": [{"start": 0, "end": 1.2, "text": WALK},
                                             {"start": 0.8, "end": 2, "text": "a person turns left"}],
                                "parts": [{"parts": ["left_arm"], "text": WAVE, "start": 0.5}]}))
    main(["generate", "--ckpt", str(controlnet_ckpt["controlnet"]), "--timeline", str(path), "--num_samples", "2",
          "--steps", "2", "--no_preview", "--out", str(tmp_path / "out")])
    settings = json.loads((tmp_path / "out/generation.json").read_text())
    assert settings["frames"] == 40 and settings["length_s"] == 2.0  # the timeline's end
    assert settings["timeline"]["timeline"][1] == {"start": 0.8, "end": 2.0, "text": "a person turns left"}
    assert settings["timeline"]["parts"] == [{"parts": ["left_arm"], "text": WAVE, "start": 0.5}]
    assert not settings["unconditional"] and settings["guidance_scale"] == 4.5
    first, second = (np.load(tmp_path / f"out/sample_00{i}.features.npy") for i in (0, 1))
    assert first.shape == (40, 263) and not np.array_equal(first, second)
    assert generator_for(load_module(controlnet_ckpt["controlnet"])).generation_card().timeline == ("timeline",
                                                                                                    "parts")
    assert generator_for(load_module(controlnet_ckpt["pretrain"])).generation_card().timeline == ()


def test_the_parser_keeps_the_file_and_checks_against_a_motion():
    spans = parse_timeline({"timeline": [{"start": 0, "end": 2, "text": WALK}, {"start": 2, "end": 4, "text": WAVE}],
                            "transition": 1})
    assert spans.end == 4.0 and spans.kinds == ("timeline",) and spans.transition == 1.0
    assert spans.context is None and "context" not in spans.to_dict()
    cut = parse_timeline({**spans.to_dict(), "context": 0.5})
    assert cut.context == 0.5 and cut.to_dict()["context"] == 0.5
    rep = get_representation("humanml3d263", SMPL22)
    assert cut.resolve(80, FPS, rep).windows == ((0, 60), (21, 80))  # a 1-s crossing, 0.5 s on either side
    spans.check("smpl22", 4.0, FPS)
    spans.check("smpl22", 4.0 + 0.4 / FPS, FPS)  # within a frame's rounding
    with pytest.raises(UsageError, match="before the motion's end"):
        spans.check("smpl22", 5.0, FPS)


def test_bench_timeline_scores_each_segment_on_its_own_frames(controlnet_ckpt, tmp_path, capsys):
    """``omg bench timeline`` on a held-out set of two actions: timelines of two and three of its captions, a
    walk on the legs with a wave on the arms, every figure of the table there."""
    from helpers import walking_clip
    from omg.data.shards import ShardWriter
    from omg.motion import Clip
    from omg.tools.bench.timeline import bench_timeline

    clips = []
    for i, (action, text) in enumerate([("walk", "a person walks forward"), ("bye", "a person waves goodbye"),
                                        ("walk", "a person walks forward slowly"), ("bye", "a person says bye")]):
        walk = walking_clip(200 + i)
        clips.append(Clip(id=f"{action}{i}", skeleton=SMPL22, fps=FPS, positions=walk.positions, texts=[text],
                          category="human", source="test", labels={"content": action}))
    rep = get_representation("humanml3d263", SMPL22)
    ShardWriter(tmp_path / "val", rep, FPS, max_clips=8, log=lambda m: None).write(iter(clips))
    result = bench_timeline(controlnet_ckpt["controlnet"], str(tmp_path / "val"), timelines=2, compositions=1,
                            samples=2, steps=2, segment_seconds=1.0, composition_seconds=1.0)
    assert [len(t) for t in result["timelines"]] == [2, 3]
    for timeline in result["timelines"]:
        assert all(("walk" in a) != ("walk" in b) for a, b in zip(timeline, timeline[1:]))  # neighbours differ
    assert len(result["segments"]) == 5 and all(len(r["passed"]) == 2 for r in result["segments"])
    assert set(result["alone"]) == {r["text"] for r in result["segments"]}
    assert result["jerk"]["real"] > 0 and result["jerk"]["boundary"] > 0
    (composition,) = result["compositions"]
    assert composition["arm"] == "arms" and "walks" in composition["walk"] and "and" in composition["sentence"]
    assert set(result["seconds_per_motion_second"]) == {"timeline", "plain", "parts"}
    out = capsys.readouterr().out
    assert "| segments passing, in timelines / alone |" in out and "| body-part compositions: both parts" in out
    # a subset of the same run: the second timeline's captions and seeds, each text seeing its own stretch
    second = bench_timeline(controlnet_ckpt["controlnet"], str(tmp_path / "val"), timelines=2, compositions=0,
                            samples=2, steps=2, segment_seconds=1.0, context=0.25, only_timelines=(2,))
    assert second["timelines"] == result["timelines"][1:] and not second["compositions"]
    assert [r["timeline"] for r in second["segments"]] == [2, 2, 2]
    assert second["alone"] == {text: result["alone"][text] for text in second["alone"]}  # the same seeds
    with pytest.raises(UsageError, match="--only_timelines: 3 is past the 2 the run makes"):
        bench_timeline(controlnet_ckpt["controlnet"], str(tmp_path / "val"), timelines=2, only_timelines=(3,))
    # the same composition with separate chains, sampled alone (no timeline), its foot skating beside the plain's
    split = bench_timeline(controlnet_ckpt["controlnet"], str(tmp_path / "val"), timelines=2, compositions=1,
                           samples=2, steps=2, segment_seconds=1.0, composition_seconds=1.0, chains="separate",
                           coupling=0.5, only_compositions=(1,))
    assert not split["segments"] and split["compositions"][0]["walk"] == composition["walk"]
    assert split["compositions"][0]["plain"] == composition["plain"]  # the same seeds, the plain sentence as before
    assert split["compositions"][0]["parts"]["skating"] >= 0 and "parts" in split["seconds_per_motion_second"]
    for chains, coupling, context, message in (("split", 0.0, None, "--chains must be one of joint, separate"),
                                               ("joint", 0.5, None, "--coupling 0.5: a number in [0, 1], with "
                                                                    "--chains separate")):
        with pytest.raises(UsageError, match=re.escape(message)):
            bench_timeline(controlnet_ckpt["controlnet"], str(tmp_path / "val"), chains=chains, coupling=coupling,
                           context=context)


# -- separate chains -------------------------------------------------------------------------------------------


def _parts(controlnet, frames: int, **how):
    return resolve_timeline([], [PartText(("legs", "root"), WALK), PartText(("left_arm",), WAVE)], frames, FPS,
                            controlnet.representation, **how)


def test_separate_independent_chains_give_each_part_its_own_text_sampled_alone(controlnet):
    """``chains="separate"``, coupling 0: each text's chain is that text sampled alone from the same noise, and
    the motion takes each part's features from its own text's chain (SINC's splice); the joint blend does not."""
    frames, seeds = 40, (5, 6)
    arm = torch.isin(torch.as_tensor(controlnet.representation.channel_joints()),
                     torch.tensor(body_parts(SMPL22)["left_arm"]))  # (D,)
    settings = SamplingSettings(steps=4, seeds=seeds, use_ema=False)
    walk, wave = (controlnet.sample([text] * 2, [frames] * 2, settings) for text in (WALK, WAVE))
    split = controlnet.sample(None, [frames] * 2, replace(settings, timeline=_parts(controlnet, frames,
                                                                                   chains="separate", coupling=0.0)))
    assert torch.allclose(split[..., ~arm], walk[..., ~arm], atol=1e-4)
    assert torch.allclose(split[..., arm], wave[..., arm], atol=1e-4)
    joint = controlnet.sample(None, [frames] * 2, replace(settings, timeline=_parts(controlnet, frames)))
    assert not torch.allclose(joint[..., ~arm], walk[..., ~arm], atol=1e-2)  # the joint blend reads the wave's arm


def test_fully_coupled_chains_are_the_joint_blend_and_coupling_sits_between(controlnet):
    """Coupling 1 gives every chain the composed estimate: the chains never part and the motion is the joint
    blend's; a coupling between moves the motion away from both ends."""
    frames = 40
    settings = SamplingSettings(steps=4, seed=3, use_ema=False)
    joint = controlnet.sample(None, [frames] * 2, replace(settings, timeline=_parts(controlnet, frames)))
    coupled, half, apart = (controlnet.sample(None, [frames] * 2, replace(settings, timeline=_parts(
        controlnet, frames, chains="separate", coupling=c))) for c in (1.0, 0.5, 0.0))
    assert torch.allclose(coupled, joint, atol=1e-5)
    assert not torch.allclose(half, joint, atol=1e-3) and not torch.allclose(half, apart, atol=1e-3)


def test_separate_chains_sample_with_every_sampler_guidance_stance_root_and_control(controlnet):
    from omg.lit.control import Control
    from omg.registry import SAMPLERS

    frames = 40
    timeline = _parts(controlnet, frames, chains="separate", coupling=0.25)
    for sampler in SAMPLERS.names():
        motion = controlnet.sample(None, [frames, frames - 6], SamplingSettings(
            steps=3, sampler=sampler, use_ema=True, timeline=timeline, stance_root=0.5, guidance=2.0))
        assert motion.shape == (2, frames, 263) and torch.isfinite(motion).all(), sampler
    # a hand target per motion: every chain steered towards it, the motion's left wrist near it
    wrist = SMPL22.names.index("left_wrist")
    targets = torch.zeros(2, frames, 22, 3)
    targets[:, -1, wrist] = torch.tensor([0.3, 1.6, 0.2])
    weights = torch.zeros(2, frames, 22)
    weights[:, -1, wrist] = 1.0
    control = Control(targets=targets, axes=torch.ones(2, frames, 22, 3, dtype=torch.bool), weights=weights,
                      tolerance=torch.zeros(2, frames, 22), groups=(weights > 0).long() - 1, names=("hand",))
    free, steered = (controlnet.sample(None, [frames] * 2, SamplingSettings(
        steps=4, use_ema=False, timeline=timeline, control=c)) for c in (None, control))
    miss = [(controlnet.representation.decode(m)[:, -1, wrist] - targets[:, -1, wrist]).norm(dim=-1).mean()
            for m in (free, steered)]
    assert miss[1] < 0.5 * miss[0], miss


def test_chains_in_the_file_are_checked_in_one_line_and_recorded():
    parts = [{"parts": ["legs", "root"], "text": WALK}, {"parts": ["left_arm"], "text": WAVE}]
    spans = parse_timeline({"parts": parts, "chains": "separate", "coupling": 0.25})
    assert spans.chains == "separate" and spans.coupling == 0.25
    assert parse_timeline({"parts": parts, "chains": "separate"}).coupling == DEFAULT_COUPLING
    assert spans.to_dict()["chains"] == "separate" and parse_timeline(spans.to_dict()) == spans
    assert "chains" not in parse_timeline({"parts": parts}).to_dict()  # the joint blend, recorded as before
    rep = get_representation("humanml3d263", SMPL22)
    assert spans.resolve(40, FPS, rep).separate and not parse_timeline({"parts": parts}).resolve(40, FPS, rep).separate
    cut = parse_timeline({"parts": [*parts[:1], {**parts[1], "start": 1}], "chains": "separate", "context": 0.25})
    assert cut.to_dict()["context"] == 0.25 and parse_timeline(cut.to_dict()) == cut
    assert cut.resolve(40, FPS, rep).separate and cut.resolve(40, FPS, rep).windows == ((0, 40), (11, 40))
    for extra, message in (({"chains": "split"}, "timeline: chains must be one of joint, separate, got 'split'"),
                           ({"chains": "separate", "coupling": 2}, "coupling must be a number in [0, 1], got 2"),
                           ({"coupling": 0.5}, "coupling pulls separate chains together")):
        with pytest.raises(UsageError) as e:
            parse_timeline({"parts": parts, **extra})
        assert message in str(e.value) and "\n" not in str(e.value)


def test_omg_generate_takes_separate_chains_from_the_file(controlnet_ckpt, tmp_path):
    from omg.cli import main

    path = tmp_path / "t.json"
    timeline = {"parts": [{"parts": ["legs", "root"], "text": WALK}, {"parts": ["left_arm"], "text": WAVE}],
                "chains": "separate", "coupling": 0.5, "context": 0.25}
    path.write_text(json.dumps(timeline))
    main(["generate", "--ckpt", str(controlnet_ckpt["controlnet"]), "--timeline", str(path), "--num_samples", "2",
          "--steps", "2", "--length", "2", "--no_preview", "--out", str(tmp_path / "out")])
    recorded = json.loads((tmp_path / "out/generation.json").read_text())["timeline"]
    assert recorded["chains"] == "separate" and recorded["coupling"] == 0.5 and recorded["context"] == 0.25
    assert np.load(tmp_path / "out/sample_000.features.npy").shape == (40, 263)


# -- separate chains with a context --------------------------------------------------------------------------------

SPANS = [Segment(0, 1, WALK), Segment(1, 2, WAVE)]


def test_separate_chains_whose_context_covers_the_motion_are_the_chains_without_one(controlnet):
    """Bitwise: a window of every frame cuts out the whole chain (a copy of its frames and real-frame mask), puts
    the estimate back in full and leaves no frame outside it, so every step computes the same numbers. Likewise
    context 0 on a composition of parts that each hold the whole motion: their windows are the whole motion."""
    frames = 40
    settings = SamplingSettings(steps=3, seed=7, use_ema=False, stance_root=0.5)
    rep, chains = controlnet.representation, {"chains": "separate", "coupling": 0.25}
    whole_parts = [PartText(("legs", "root"), WALK), PartText(("arms",), WAVE)]
    for segments, parts, context in ((SPANS, [], frames / FPS), ([], whole_parts, 0.0)):
        windowed = resolve_timeline(segments, parts, frames, FPS, rep, context=context, **chains)
        assert windowed.windows == ((0, frames),) * 2
        alike = [controlnet.sample(None, [frames, frames - 6], replace(settings, timeline=t))
                 for t in (windowed, resolve_timeline(segments, parts, frames, FPS, rep, **chains))]
        assert torch.equal(*alike), context


def test_with_a_context_each_chain_sees_only_its_own_window_and_carries_the_join_outside_it(controlnet):
    """``chains_denoiser`` with windows: chain k's text denoises only its window of chain k (what the chain
    holds outside it cannot change its estimate there, coupling 0); outside its window a chain's estimate is
    the composed one; inside it, its own pulled towards the composed by the coupling."""
    from omg.lit.timeline import chains_denoiser, join

    frames, rep = 80, controlnet.representation
    segments = [Segment(0, 2, WALK), Segment(2, 4, WAVE)]
    apart, half = (resolve_timeline(segments, [], frames, FPS, rep, context=0.5, chains="separate", coupling=c)
                   for c in (0.0, 0.5))
    assert apart.windows == ((0, 55), (26, 80))
    mask = length_mask([frames, frames])
    gen = torch.Generator().manual_seed(8)
    x, t = torch.randn(4, frames, 263, generator=gen), torch.tensor([400, 800] * 2)  # chain k of motion b: k·2+b
    later = x.clone()
    later[:2, 60:] = torch.randn(2, 20, 263, generator=gen)  # the walk's chain past its window
    with torch.no_grad():
        step = chains_denoiser(controlnet.denoiser, apart, mask, None)
        a, b = step(x, t).unflatten(0, (2, 2)), step(later, t).unflatten(0, (2, 2))
        walk_cut = _estimates(controlnet, [WALK] * 2, length_mask([55, 55]), x[:2, :55], t[:2])
        wave_cut = _estimates(controlnet, [WAVE] * 2, length_mask([54, 54]), x[2:, 26:], t[2:])
        assert torch.allclose(a[0, :, :55], walk_cut, atol=1e-5) and torch.allclose(a[1, :, 26:], wave_cut,
                                                                                     atol=1e-5)
        assert torch.equal(a[0, :, :55], b[0, :, :55])  # blind to its chain's frames 60..79
        composed = join(torch.stack([torch.cat([walk_cut, torch.zeros(2, 25, 263)], 1),
                                     torch.cat([torch.zeros(2, 26, 263), wave_cut], 1)]), apart.weights[:, None])
        assert torch.allclose(a[0, :, 55:], composed[:, 55:], atol=1e-5)  # outside its window: the join
        assert torch.allclose(a[1, :, :26], composed[:, :26], atol=1e-5)
        pulled = chains_denoiser(controlnet.denoiser, half, mask, None)(x, t).unflatten(0, (2, 2))
        assert torch.allclose(pulled[0, :, :55], 0.5 * (walk_cut + composed[:, :55]), atol=1e-5)


def test_fully_coupled_chains_with_a_context_are_the_joint_blend_with_it(controlnet):
    frames, rep = 40, controlnet.representation
    settings = SamplingSettings(steps=4, seed=3, use_ema=False)
    joint, coupled, apart = (controlnet.sample(None, [frames] * 2, replace(settings, timeline=resolve_timeline(
        SPANS, [], frames, FPS, rep, context=0.25, **how))) for how in (
            {}, {"chains": "separate", "coupling": 1.0}, {"chains": "separate", "coupling": 0.0}))
    assert torch.allclose(coupled, joint, atol=1e-5) and not torch.allclose(apart, joint, atol=1e-3)


def test_separate_chains_with_a_context_sample_with_every_sampler(controlnet):
    from omg.registry import SAMPLERS

    frames = 40
    rep = controlnet.representation
    timeline = resolve_timeline(SPANS, [PartText(("left_arm",), "a person raises the left arm", start=0.5)], frames,
                                FPS, rep, context=0.25, chains="separate", coupling=0.25)
    assert timeline.windows == ((0, 30), (11, 40), (1, 40))  # each text its own stretch (+ 0.25 s)
    without = replace(timeline, windows=None)
    for sampler in SAMPLERS.names():
        settings = SamplingSettings(steps=3, sampler=sampler, use_ema=True, stance_root=0.5, guidance=2.0, seed=1)
        motion = controlnet.sample(None, [frames, frames - 6], replace(settings, timeline=timeline))
        assert motion.shape == (2, frames, 263) and torch.isfinite(motion).all(), sampler
        assert not torch.allclose(motion, controlnet.sample(None, [frames, frames - 6],
                                                            replace(settings, timeline=without)), atol=1e-4), sampler


# -- smoothing ---------------------------------------------------------------------------------------------------


def _jerk(x: torch.Tensor) -> float:
    return float(torch.diff(x, n=3, dim=1).abs().mean())


def test_smoothing_removes_frame_to_frame_shake_and_keeps_slow_motion_contacts_and_padding():
    """``omg.lit.control.smoothed``: a jittery estimate loses most of its jerk, a slow one barely moves, the
    contact channels and the frames past a motion's length stay as they are, and a motion smooths alike alone or
    beside a longer one."""
    from omg.lit.control import smoothed

    frames, torch_gen = 60, torch.Generator().manual_seed(0)
    t = torch.arange(frames, dtype=torch.float32)[None, :, None]  # (1, T, 1)
    slow = torch.sin(2 * torch.pi * t / 40).expand(2, frames, 6).clone()  # 0.5 Hz at 20 fps
    shaky = slow + 0.1 * torch.randn(2, frames, 6, generator=torch_gen)
    mask = length_mask([frames, frames - 10])
    fixed = (5,)
    for x0 in (slow, shaky):
        x0[1, frames - 10:] = 0.0  # padding, as the sampler keeps it
    out = {name: smoothed(lambda x, t: x, 1.5, mask, fixed)(x0, torch.zeros(2)) for name, x0 in
           (("slow", slow), ("shaky", shaky))}
    assert _jerk(out["shaky"][:, :frames - 10, :5]) < 0.05 * _jerk(shaky[:, :frames - 10, :5])
    inner = slice(5, frames - 15)  # away from the edges, where the Gaussian is cut
    assert (out["slow"][:, inner] - slow[:, inner]).abs().max() < 0.03
    assert torch.equal(out["shaky"][..., 5], shaky[..., 5])  # a contact channel
    assert torch.equal(out["shaky"][1, frames - 10:], shaky[1, frames - 10:])  # padding
    alone = smoothed(lambda x, t: x, 1.5, length_mask([frames - 10]), fixed)(shaky[1:, :frames - 10], torch.zeros(1))
    assert torch.allclose(alone[0], out["shaky"][1, :frames - 10], atol=1e-6)
    assert smoothed(lambda x, t: x, 0.0, mask, fixed)(shaky, torch.zeros(2)) is shaky  # 0: off


def test_smoothing_lowers_a_samples_jerk_with_every_sampler_a_timeline_and_stance_root(controlnet):
    """``SamplingSettings(smoothing=...)``: every registered sampler, plain, on a timeline and with stance_root,
    gives a motion whose joints shake less than the same sample without it; 0 is the plain path, bitwise."""
    from omg.registry import SAMPLERS

    frames, rep = 40, controlnet.representation
    two = resolve_timeline([Segment(0, 1, WALK), Segment(1, 2, WAVE)], [], frames, FPS, rep)
    plain = SamplingSettings(steps=3, seeds=(1, 2), use_ema=False)
    assert torch.equal(controlnet.sample([WALK, WAVE], [frames] * 2, plain),
                       controlnet.sample([WALK, WAVE], [frames] * 2, replace(plain, smoothing=0.0)))
    for sampler in SAMPLERS.names():
        for texts, how in (([WALK, WAVE], {}), (None, {"timeline": two, "stance_root": 0.5})):
            rough, smooth = (controlnet.sample(texts, [frames, frames - 6], replace(
                plain, sampler=sampler, smoothing=s, **how)) for s in (0.0, 1.5))
            assert torch.isfinite(smooth).all() and smooth.shape == (2, frames, 263)
            jerk = [_jerk(rep.decode(m[:1]).flatten(2)) for m in (rough, smooth)]
            assert jerk[1] < 0.5 * jerk[0], (sampler, how.keys(), jerk)


@pytest.mark.parametrize("value", [-1.0, float("nan"), 10.5, True, "2"])
def test_a_bad_smoothing_is_one_line(value):
    with pytest.raises(UsageError, match=r"^EvalCallback.smoothing must be a number of frames in \[0, 10\] \(0: off\)"):
        SamplingSettings(smoothing=value, key="EvalCallback")
