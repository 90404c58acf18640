"""Spatial control (issue #38's spatial half): the constraints file read and checked in one line per error, every
sampler steered onto keyframes, joint targets and root paths that unconstrained sampling misses, sampling without
constraints untouched, and the routes: ``omg generate --constraints`` and ``omg serve``'s ``constraints``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from helpers import TINY_DIT
from helpers.checkpoints import SPEC, save_module
from omg.errors import UsageError
from omg.generation.control import KINDS, read_constraints
from omg.generation.protocol import GenerationCard
from omg.lit.control import constraint_errors
from omg.lit.pretrain import PretrainModule
from omg.lit.sampling import SamplingSettings

CARD = GenerationCard(family="omg", skeleton="smpl22", representation="humanml3d263", fps=20.0,
                      inputs=("text", "unconditional"), constraints=KINDS, contacts=("model", "ground"))
FRAMES = 40  # 2 s at 20 fps
BVH = Path(__file__).parent.parent / "../shared/data/motion/human/bandai1/dataset-1_bow_normal_001.bvh"
TWO_JOINT_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.05
0 90 0 0 0 0 0 0 0
0 90 0 0 0 0 0 0 0
"""


def _module() -> PretrainModule:
    """An untrained mini prior with random weights and the mini shards' feature statistics: its samples go
    anywhere, so only steering meets a target."""
    stats = json.loads((Path(__file__).parent.parent / "shards/mini/human263/train/manifest.json").read_text())
    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec={**SPEC, "mean": stats["mean"], "std": stats["std"]},
                            ema_decay=0)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    return module.eval()


@pytest.fixture(scope="module")
def module() -> PretrainModule:
    return _module()


@pytest.fixture(scope="module")
def pretrain_ckpt(tmp_path_factory, module) -> Path:
    ckpt = tmp_path_factory.mktemp("control") / "pre.ckpt"
    save_module(module, ckpt)
    return ckpt


def _error(spec, card: GenerationCard = CARD) -> str:
    with pytest.raises(UsageError) as e:
        read_constraints(spec, card, FRAMES, "constraints", allow_files=False)  # as a request is read
    message = str(e.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize("spec, message", [
    ({"targets": [{"joint": "right_wrist", "time": 2.5, "position": [0, 1, 0]}]},
     "constraints: targets[0].time 2.5 s is outside the motion (0..2 s)"),
    ({"targets": [{"joint": "rigth_wrist", "time": 1, "position": [0, 1, 0]}]},
     "constraints: targets[0].joint 'rigth_wrist' is not a joint of smpl22 (pelvis, left_hip"),
    ({"targets": [{"joint": "right_wrist", "time": 1, "position": [0, float("nan"), 0]}]},
     "constraints: targets[0].position[1] must be a finite number, got nan"),
    ({"targets": [{"joint": "right_wrist", "span": [1.5, 0.5], "position": [0, 1, 0]}]},
     "constraints: targets[0].span ends before it starts (1.5 > 0.5)"),
    ({"targets": [{"joint": "right_wrist", "time": 1, "position": [0, 1, 0], "axes": "w"}]},
     "constraints: targets[0].axes must name some of x, y, z"),
    ({"waypoints": [{"position": [1, 1], "time": 1.5}, {"position": [2, 2], "time": 0.5}]},
     "constraints: waypoints[1] comes before the waypoint listed ahead of it"),
    ({"keyframes": [{"time": 1, "positions": [[0, 1, 0]] * 3}]},
     "constraints: keyframes[0].positions must list [x, y, z] for each of the 22 joints of smpl22"),
    ({"keyframes": [{"time": 1, "file": "take.bvh"}]},
     "constraints: keyframes[0].file: a request names no file; give joints or positions"),
    ({"facing": [{"time": 1, "direction": [0, 0]}]}, "constraints: facing[0].direction [0, 0] points nowhere"),
    ({"contacts": [{"joint": "left_wrist", "span": [0, 1]}]}, "constraints: contacts[0].joint 'left_wrist' is no foot"),
    ({"timeline": [{"start": 0, "end": 1, "text": "a person walks"}]},
     "constraints: 'timeline' is a prompt timeline's key: use --timeline for it"),
    ({"parts": []}, "constraints: 'parts' is a prompt timeline's key: use --timeline for it"),
    ({"trajectory": []}, "constraints: unknown key 'trajectory'"),
    ({"targets": [{"joint": "right_wrist", "time": 1, "position": [0, 1, 0], "weight": -1}]},
     "constraints: targets[0].weight must be in [0, 1e+06], got -1"),
    ({"steering": {"curvature": 2}}, "constraints: steering.curvature must be in [0, 1], got 2"),
])
def test_bad_constraints_are_one_line(spec, message):
    assert _error(spec).startswith(message)


def test_a_card_without_constraints_refuses_them_and_a_file_is_read_with_its_rows(tmp_path):
    animal = GenerationCard(family="habit", skeleton="smal35", representation="quatvel", fps=30.0,
                            inputs=("motion",))
    assert _error({"targets": []}, animal) == ("constraints: this habit model takes no constraints (its generation "
                                               "card lists none)")
    path = tmp_path / "c.json"
    path.write_text('{"targets": [{"joint": "right_wrist", "time": 1, "position": [0, NaN, 0]}]}')
    with pytest.raises(UsageError, match=r"^--constraints .*c.json: holds NaN, which is no position"):
        read_constraints(path, CARD, FRAMES)
    path.write_text('{"targets": [')
    with pytest.raises(UsageError, match=r"^--constraints .*c.json: not JSON"):
        read_constraints(path, CARD, FRAMES)
    rig = tmp_path / "two.bvh"  # a rig no joint map fits
    rig.write_text(TWO_JOINT_BVH)
    path.write_text(json.dumps({"keyframes": [{"time": 1, "file": "two.bvh"}]}))
    with pytest.raises(UsageError) as e:
        read_constraints(path, CARD, FRAMES)
    assert "\n" not in str(e.value) and "keyframes[0].file" in str(e.value), str(e.value)


def test_the_models_own_contacts_need_contact_channels():
    """A card lists the feet a file may ask held (``contact_sources``): the model's contact channels where its
    representation has them, the feet on the ground wherever its skeleton has feet."""
    from omg.generation.control import contact_sources
    from omg.motion import get_representation

    assert contact_sources(get_representation("humanml3d263", "smpl22")) == CARD.contacts == ("model", "ground")
    quatvel = GenerationCard(family="omg", skeleton="smpl22", representation="quatvel", fps=20.0,
                             inputs=("unconditional",), constraints=KINDS,
                             contacts=contact_sources(get_representation("quatvel", "smpl22")))
    assert quatvel.contacts == ("ground",)
    assert _error({"contacts": "model"}, quatvel) == ('constraints: contacts: "model" needs contact channels, which '
                                                      'representation quatvel has none of: give the feet\'s spans or '
                                                      '"ground"')
    assert read_constraints({"contacts": "model"}, CARD, FRAMES, allow_files=False)[0].own_contacts
    ground = read_constraints({"contacts": "ground"}, quatvel, FRAMES, allow_files=False)[0]
    assert ground.ground_contacts and not ground.own_contacts and ground.fps == 20.0 and ground.contacts is None
    both = read_constraints({"contacts": ["model", "ground", {"joint": "left_foot", "span": [0.5, 1.0]}]}, CARD,
                            FRAMES, allow_files=False)[0]
    assert both.own_contacts and both.ground_contacts and both.contacts[0, :, 1].nonzero().flatten().tolist() == \
        list(range(10, 21))  # left_foot, the second of smpl22's feet, planted 0.5 s to 1.0 s
    assert _error({"contacts": ["model", "floor"]}) == (
        'constraints: contacts[1] is none of "model" (the model\'s own contact channels), "ground" (the feet each '
        "estimate puts on the ground) or {joint, span}")


def test_ground_feet_are_low_and_slow_on_each_motions_own_frames():
    """A foot on the ground (within the band of the motion's lowest foot heights) and slower than the clean-up's
    speed is held; a low foot sliding fast, a raised one, and a padded frame are not."""
    from omg.lit.control import ground_feet
    from omg.skeleton import get_skeleton

    skeleton = get_skeleton("smpl22")
    feet = list(skeleton.feet)
    joints = torch.zeros(2, 10, 22, 3)
    joints[..., 1] = 1.0  # every joint a metre up
    joints[:, :, feet, 1] = 0.02  # the feet on the floor, still
    joints[0, :, feet[0], 0] = torch.arange(10) * 0.1  # the first foot sliding 2 m/s at 20 fps
    joints[0, 5:, feet[1], 1] = 0.5  # the second raised half a metre from frame 5
    mask = torch.ones(2, 10, dtype=torch.bool)
    mask[1, 6:] = False  # the second motion has 6 frames
    held = ground_feet(joints, mask, skeleton, fps=20.0)  # (2, 10, F)
    assert not held[0, :, 0].any() and held[0, :4, 1].all() and not held[0, 5:, 1].any()
    assert held[0, :, 2:].all() and held[1, :6].all() and not held[1, 6:].any()


def test_free_waypoints_are_timed_by_the_length_of_the_path():
    control, _ = read_constraints({"waypoints": [{"position": [0, 1]}, {"position": [0, 2], "time": 1.0},
                                                 {"position": [0, 3]}]}, CARD, FRAMES)
    root = control.weights[0, :, 0] > 0
    frames = root.nonzero().squeeze(1).tolist()
    assert frames == [10, 20, 39]  # halfway to the timed one (1 m of 2), then the motion's end
    assert control.targets[0, 10, 0, 2] == 1 and control.targets[0, 39, 0, 2] == 3


@pytest.mark.skipif(not BVH.exists(), reason="needs ../shared's Bandai-Namco takes")
def test_a_keyframe_from_a_bvh_frame_is_the_takes_pose_where_the_take_puts_it(tmp_path):
    from omg.generation.read import read_source_motion
    from omg.motion import get_representation
    from omg.skeleton import get_skeleton

    spec = {"keyframes": [{"time": 1, "file": str(BVH.resolve()), "frame": 30, "root": [0.5, 1.0]}]}
    control, _ = read_constraints(spec, CARD, FRAMES)
    take = read_source_motion(BVH, get_skeleton("smpl22"), 20.0, None, "take")
    pose = get_representation("humanml3d263", "smpl22").canonicalize(take.positions)[30]
    got = control.targets[0, 20].numpy()
    assert np.allclose(got[0, [0, 2]], [0.5, 1.0]) and control.axes[0, 20].all()
    assert np.allclose(got - got[0], pose - pose[0], atol=1e-5)  # the take's own pose around its root


def _spec() -> dict:
    return {"keyframes": [{"time": 1.0, "joints": {"left_wrist": [0.4, 1.3, 0.6], "head": [0.0, 1.6, 0.5]}}],
            "targets": [{"joint": "right_wrist", "span": [1.5, 1.8], "position": [None, 1.7, None], "axes": "y"}],
            "path": {"points": [[0, 0], [0.5, 1.0], [1.0, 2.0]]}}


@pytest.mark.parametrize("sampler", ["ddim", "dpmpp", "euler"])
def test_every_sampler_is_steered_onto_the_targets_unconstrained_sampling_misses(module, sampler):
    control, _ = read_constraints(_spec(), CARD, FRAMES)
    settings = SamplingSettings(steps=4, sampler=sampler, use_ema=False, seed=3)
    free = module.representation.decode(module.sample(None, [FRAMES] * 2, settings))
    steered = module.representation.decode(module.sample(None, [FRAMES] * 2, SamplingSettings(
        steps=4, sampler=sampler, use_ema=False, seed=3, control=control)))
    for row_free, row in zip(constraint_errors(free, control), constraint_errors(steered, control)):
        assert set(row) == {"keyframes[0]", "targets[0]", "path"}
        assert max(row.values()) < 0.01, row  # within 1 cm
        assert min(row_free.values()) > 0.05, row_free  # which sampling alone does not come near


def test_steered_sampling_reports_the_samplers_steps_and_the_same_motion(module):
    """Steering re-solves every estimate (its own iterations, no sampler step): the sampler reports its 4 steps,
    and watching it changes no number."""
    control, _ = read_constraints(_spec(), CARD, FRAMES)
    settings = SamplingSettings(steps=4, use_ema=False, seed=3, control=control)
    heard = []
    watched = module.sample(None, [FRAMES], settings, progress=lambda *step: heard.append(step))
    assert heard == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert torch.equal(watched, module.sample(None, [FRAMES], settings))


def test_a_planted_foot_stays_still_while_the_root_walks_a_path(module):
    """The left foot planted for half a second while the path walks on: held at one place in the world in the
    same solve as the path (a step residual, coupling each frame to the next, left it sliding 23 cm with the
    root here, 14 cm from one place at worst), the path met all the same."""
    feet = {"left_ankle": 7, "left_foot": 10}
    spec = {"path": {"points": [[0, 0], [0, 2]]},
            "contacts": [{"joint": name, "span": [0.5, 1.0]} for name in feet]}
    control, _ = read_constraints(spec, CARD, FRAMES)
    settings = SamplingSettings(steps=4, use_ema=False, seed=3, control=control)
    joints = module.representation.decode(module.sample(None, [FRAMES] * 2, settings))
    planted = joints[:, 10:21, list(feet.values())]  # (2, 11, 2, 3) frames 0.5 s to 1.0 s
    assert (planted - planted.mean(1, keepdim=True)).norm(dim=-1).max() < 0.003  # within 3 mm of one place
    for row in constraint_errors(joints, control):
        assert row["path"] < 0.01, row
    free = module.representation.decode(module.sample(None, [FRAMES] * 2, SamplingSettings(
        steps=4, use_ema=False, seed=3, control=read_constraints({"path": spec["path"]}, CARD, FRAMES)[0])))
    slid = free[:, 10:21, list(feet.values())]
    assert (slid - slid.mean(1, keepdim=True)).norm(dim=-1).max() > 0.1  # the path alone slides it


def test_a_held_foot_is_set_down_and_lifted_off_over_the_eased_frames():
    """The frames just before a stretch of planted frames and just after it hold the foot on the ground at the
    stretch's place with a weight falling 2/3, 1/3 (as the foot clean-up eases its pin); its height free; a
    frame between two stretches takes the nearer one's place (as near to both: the next); the stretches as they
    were."""
    from omg.lit.control import eased

    hold = torch.full((1, 12, 1, 3), math.nan)
    hold[0, 3:6, 0] = torch.tensor([1.0, 0.0, 2.0])  # a stretch on frames 3..5
    hold[0, 9:11, 0] = torch.tensor([4.0, 0.0, 5.0])  # another on frames 9..10
    out, weight = eased(hold, 2)
    assert weight[0, :, 0, 0].tolist() == pytest.approx([0, 1 / 3, 2 / 3, 1, 1, 1, 2 / 3, 1 / 3, 2 / 3, 1, 1, 2 / 3])
    assert out[0, 3:6].equal(hold[0, 3:6]) and out[0, 9:11].equal(hold[0, 9:11])
    assert out[0, [1, 2, 6], 0, 0].tolist() == [1.0, 1.0, 1.0] and out[0, [8, 11], 0, 2].tolist() == [5.0, 5.0]
    assert out[0, 7, 0, 0] == 4.0  # as near to both: the place it lands at next
    assert out[0, [1, 2, 6, 7, 8, 11], 0, 1].isnan().all() and out[0, 0].isnan().all()


def test_planted_feet_and_targets_are_both_met_by_the_steerings_defaults(module):
    """The model's own planted feet held while a path, a wrist over the whole motion and a keyframe pull the
    body: the last estimates' solve (``final_iterations``, default) meets both to the millimetre, where a quarter
    of its iterations left the feet 6 cm from their places and the targets 9 mm off."""
    from omg.lit.control import STRIDE, held_feet, leg_length, planted_feet

    spec = {**_spec(), "targets": [{"joint": "right_wrist", "span": [0, 2], "position": [0.3, 1.4, 0.8]}],
            "contacts": "model"}
    control, _ = read_constraints(spec, CARD, FRAMES)
    features = module.sample(None, [FRAMES] * 2, SamplingSettings(steps=4, use_ema=False, seed=3, control=control))
    rep = module.representation
    joints, feet = rep.decode(features), list(rep.skeleton.feet)
    planted = planted_feet(features, joints, control, rep, torch.ones(2, FRAMES, dtype=torch.bool))
    hold = held_feet(joints, planted, control, feet, STRIDE * leg_length(rep.skeleton))  # (2, T, F, 3)
    assert hold.isfinite().any(), "the untrained prior plants its feet"
    assert (joints[:, :, feet] - hold).norm(dim=-1)[hold[..., 0].isfinite()].max() < 0.001
    for row in constraint_errors(joints, control):
        assert max(row.values()) < 0.001, row


def test_curvature_bends_the_frames_around_a_keyframe_instead_of_its_own_alone(module):
    """``steering.curvature`` weighs the change's bend from frame to frame in the solve: the joints' jerk around
    a keyframe falls (the frames next to it move part of the way with it), the keyframe met all the same."""
    from omg.tools.bench.timeline import joint_jerk

    spec = {"keyframes": _spec()["keyframes"]}  # at 1 s: frame 20
    jerks = {}
    for curvature in (0.0, 0.0003):
        control, _ = read_constraints({**spec, "steering": {"curvature": curvature}}, CARD, FRAMES)
        joints = module.representation.decode(module.sample(None, [FRAMES] * 2, SamplingSettings(
            steps=4, use_ema=False, seed=3, control=control)))
        for row in constraint_errors(joints, control):
            assert row["keyframes[0]"] < 0.01, row
        jerk = torch.stack([joint_jerk(j, CARD.fps) for j in joints])  # (2, T - 3), frame t + 1.5 at the middle
        jerks[curvature] = float(jerk[:, 16:22].mean())  # the windows around frame 20
    assert jerks[0.0003] < 0.8 * jerks[0.0], jerks


def test_sampling_without_constraints_never_steers(module, monkeypatch):
    import omg.lit.pretrain as pretrain

    settings = SamplingSettings(steps=3, use_ema=False)
    before = module.sample(None, [FRAMES], settings)
    monkeypatch.setattr(pretrain, "steered", lambda *a, **k: pytest.fail("steered without constraints"))
    assert torch.equal(module.sample(None, [FRAMES], settings), before)


GENERATE = ["generate", "--unconditional", "--num_samples", "2", "--length", "2", "--steps", "3", "--no_preview"]


def test_generate_takes_constraints_records_the_error_and_warns_of_one_it_cannot_meet(pretrain_ckpt, tmp_path,
                                                                                        capsys):
    from omg.cli import main

    path = tmp_path / "c.json"
    path.write_text(json.dumps(_spec()))
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--constraints", str(path), "--out", str(tmp_path / "met")])
    assert "warning" not in capsys.readouterr().err
    settings = json.loads((tmp_path / "met/generation.json").read_text())
    assert settings["constraints"] == _spec()
    for record in settings["samples"]:
        assert max(record["control_error_m"].values()) < 0.01 and record["control_unmet"] == {}
    joints = np.load(tmp_path / "met/sample_000.joints.npy")
    assert abs(joints[20, 20] - [0.4, 1.3, 0.6]).max() < 0.01  # the keyframe's left wrist, as written
    # 50 m in 1 s: generated, with a warning stating the error reached (the weight of the other constraints holds
    # the root back, so the far waypoint stays beyond its tolerance)
    path.write_text(json.dumps({"waypoints": [{"position": [0, 50], "time": 1.0}], "steering": {"final_iterations": 0,
                                                                                                 "iterations": 0}}))
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--constraints", str(path), "--out", str(tmp_path / "far")])
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("motions 1-2 of 2 made in 3 steps, ")  # the progress line, then the warnings
    assert err[1].startswith("omg: warning: motion 0: waypoints[0] not met: ")
    assert err[1].endswith("cm from its target at worst")
    record = json.loads((tmp_path / "far/generation.json").read_text())["samples"][0]
    assert record["control_unmet"]["waypoints[0]"] > 40
    # a bad file: one line, nothing written
    path.write_text(json.dumps({"targets": [{"joint": "nose", "time": 1, "position": [0, 1, 0]}]}))
    with pytest.raises(SystemExit) as e:
        main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--constraints", str(path), "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith(f"omg: error: --constraints {path}: targets[0].joint 'nose' is not")
    assert err.count("\n") == 1 and not (tmp_path / "bad").exists()


def test_the_api_takes_constraints_with_the_same_checks(pretrain_ckpt, tmp_path):
    from fastapi.testclient import TestClient

    from omg.tools.serve import load_models
    from omg.tools.serve.app import Limits, create_app

    models = load_models([pretrain_ckpt], None, torch.device("cpu"))
    assert models[0].card.constraints == KINDS
    app = create_app(models, tmp_path / "results", Limits(max_batch=4, max_wait=0.05), allowed_hosts=("*",))
    with TestClient(app) as client:
        body = {"length": 2.0, "num_samples": 1, "steps": 3, "constraints": _spec()}
        answer = client.post("/v1/generate", json=body)
        assert answer.status_code == 200, answer.text
        record = answer.json()["motions"][0]["record"]
        assert max(record["control_error_m"].values()) < 0.01 and record["control_unmet"] == {}
        joints = np.asarray(answer.json()["motions"][0]["joints"])
        assert abs(joints[20, 20] - [0.4, 1.3, 0.6]).max() < 0.011
        late = {"targets": [{"joint": "right_wrist", "time": 9, "position": [0, 1, 0]}]}
        bad = client.post("/v1/generate", json={**body, "constraints": late})
        assert bad.status_code == 422 and bad.json()["detail"] == ("constraints: targets[0].time 9 s is outside the "
                                                                   "motion (0..2 s)")


def test_bench_control_measures_the_held_out_takes_met(pretrain_ckpt, h263_shards, capsys):
    from omg.tools.bench.control import bench_control

    results = bench_control(pretrain_ckpt, str(h263_shards / "val"), takes=2, steps=3, batch_size=2, max_len=40,
                            contacts=False, ground=True)  # an untrained model's contact channels plant anywhere
    free, steered = results["unconstrained"], results["constrained"]
    assert steered["within_5cm"] > 0.95 and steered["mean_cm"] < 2 and steered["path_cm"] < 2, steered
    assert free["mean_cm"] > 10 * steered["mean_cm"], free
    table = capsys.readouterr().out
    assert "| constrained |" in table and "constrained / unconstrained: foot skating" in table
    assert "every frame, feet on the ground kept still; real takes'" in table


def test_bench_control_scores_realism_with_an_evaluator(pretrain_ckpt, h263_shards, tmp_path, capsys):
    """FID and R-precision of the constrained and unconstrained motions against the held-out takes; the replay
    hands evaluate the motions in the takes' order (the takes themselves score FID 0)."""
    from omg.data.datamodule import MotionDataModule
    from omg.evaluation import build_evaluator, evaluate, parse_metrics, prompt_set
    from omg.lit.evaluator import EvaluatorModule
    from omg.tools.bench.control import _replay, bench_control

    torch.manual_seed(0)
    judge = EvaluatorModule(text_encoder="hash", flavor="mini", spec=SPEC)
    ckpt = tmp_path / "evaluator.ckpt"
    save_module(judge, ckpt)
    data = MotionDataModule(val=str(h263_shards / "val"), max_len=40, clips="whole")
    takes = prompt_set(data.val_clips().samples, 4, 0, data.windows)
    judge = build_evaluator(str(ckpt))
    scores = evaluate(_replay(takes.motions), judge, takes, parse_metrics(["fid"]), seed=0, spec=data.spec)
    assert abs(scores["fid"]) < 1e-3, scores  # the replay gave back every take once (a repeated batch would not)

    # takes of 40 to 99 frames one at a time: each batch sampled at its own length, its constraints cut to it
    results = bench_control(pretrain_ckpt, str(h263_shards / "val"), takes=4, steps=3, batch_size=1, max_len=100,
                            contacts=False, inpaint=False, evaluator=str(ckpt))
    for r in results.values():
        assert np.isfinite(r["fid"]) and r["fid"] > 0 and 0 <= r["r_precision_top3"] <= 1, r
    table = capsys.readouterr().out
    assert "| FID | R-precision top 3 |" in table and "constrained / unconstrained: FID " in table
    assert "every frame, no inpainting; real takes'" in table


def test_training_hints_are_the_clips_own_joints_on_the_kinds_and_shares_drawn():
    """A ControlNet trained with hints sees each clip's own joints (and their velocities) where a drawn constraint
    states them, nothing on padded frames, and the kinds in their shares: no hint in free_share of the clips, root
    paths on the ground alone in ground_share of them, full-body keyframes; the same generator draws the same."""
    from omg.lit.control import HintTraining, draw_hints

    B, T, J = 400, 60, 22
    joints = torch.randn(B, T, J, 3)
    mask = torch.arange(T)[None] < torch.randint(20, T + 1, (B,))[:, None]
    hints = HintTraining(enabled=True, free_share=0.25, ground_share=0.5)
    drawn = draw_hints(joints, mask, hints, torch.Generator().manual_seed(3), 20.0).view(B, T, J, 9)
    again = draw_hints(joints, mask, hints, torch.Generator().manual_seed(3), 20.0).view(B, T, J, 9)
    assert torch.equal(drawn, again)
    values, stated, velocity = drawn[..., :3], drawn[..., 3:6].bool(), drawn[..., 6:]
    assert torch.equal(values, joints * stated) and not stated[~mask].any()
    both = stated[:, 1:] & stated[:, :-1]  # a velocity where a frame and the next state the axis, in m/s
    torch.testing.assert_close(velocity[:, :-1], (joints[:, 1:] - joints[:, :-1]) * 20.0 * both)
    assert not velocity[:, -1].any() and both.any()
    per_clip = stated.flatten(1).any(1)
    assert 0.18 < 1 - per_clip.double().mean() < 0.32  # free_share, a few draws of a span aside
    root = stated[:, :, 0]  # (B, T, 3)
    paths = root.any(-1).any(-1)
    ground = paths & ~root[..., 1].any(-1)
    assert 0.3 < ground.sum() / paths.sum() < 0.7 and torch.equal(root[..., 0], root[..., 2])
    keyframes = stated.all(-1).all(-1).any(-1)  # a frame with every joint's every axis
    assert 0.1 < keyframes.double().mean() < 0.35
    heights = (stated[:, :, 1:, 1] & ~stated[:, :, 1:, 0]).any(-1).any(-1)  # a joint's height alone
    assert heights.any()
    with pytest.raises(UsageError, match="hints.free_share must be a probability"):
        HintTraining(free_share=1.5)
