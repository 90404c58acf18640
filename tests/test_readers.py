"""DeepMimic and ASF/AMC readers, read_motion dispatch and RigMotion.resample: real files from
../shared/data/motion, and tiny hand-written files whose forward kinematics is worked out here."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from omg.errors import UsageError
from omg.io.asf_amc import read_amc
from omg.io.bvh import CMU_SCALE, read_bvh
from omg.io.deepmimic import read_deepmimic
from omg.io.read import read_motion
from omg.io.rig import RigMotion


def _frames_in(path) -> list:
    return json.loads(path.read_text())["Frames"]


def test_deepmimic_humanoid(shared_motion):
    path = shared_motion / "human/deepmimic/humanoid3d_walk.txt"
    motion = read_deepmimic(path)  # character file found beside it
    frames = _frames_in(path)
    assert motion.num_joints == 15 and motion.names[:3] == ["root", "chest", "neck"]
    assert len(frames[0]) == 1 + 7 + 8 * 4 + 4 * 1  # 8 spherical, 4 revolute, 2 fixed joints
    assert len(motion) == len(frames) and motion.fps == 30.0  # 0.033332 s frames
    np.testing.assert_allclose(np.linalg.norm(motion.rotations, axis=-1), 1.0, atol=1e-9)
    np.testing.assert_allclose(motion.translations[:, 0], np.asarray(frames)[:, 1:4])
    pos = motion.positions_with_end_sites()  # joints then end sites (toe tips, head)
    names = motion.names + motion.end_site_names()
    assert {"left_ankle_end", "right_ankle_end", "neck_end"} <= set(names)
    y = {n: np.median(pos[:, i, 1]) for i, n in enumerate(names)}
    assert 0.75 < y["root"] < 0.95 and y["left_ankle_end"] < y["left_ankle"] < y["left_knee"] < y["root"]
    assert y["root"] < y["chest"] < y["neck"] < y["neck_end"] < 1.8


def test_deepmimic_dog_and_uneven_frames(shared_motion):
    dog = read_deepmimic(shared_motion / "quadruped/deepmimic_dog/dog3d_trot.txt")
    assert dog.num_joints == 23 and dog.fps == 60.0
    assert len(_frames_in(shared_motion / "quadruped/deepmimic_dog/dog3d_trot.txt")[0]) == 84
    # roll.txt has uneven frame durations: resampled to the median rate over the same time span
    path = shared_motion / "human/deepmimic/humanoid3d_roll.txt"
    durations = np.asarray(_frames_in(path))[:-1, 0]
    roll = read_deepmimic(path)
    assert roll.fps == 60.0 and len(roll) == math.floor(durations.sum() * 60 + 1e-6) + 1
    np.testing.assert_allclose(np.linalg.norm(roll.rotations, axis=-1), 1.0, atol=1e-9)


CHARACTER = {"Skeleton": {"Joints": [
    {"ID": 0, "Name": "root", "Type": "none", "Parent": -1, "AttachX": 0, "AttachY": 0, "AttachZ": 7},
    {"ID": 1, "Name": "hip", "Type": "spherical", "Parent": 0, "AttachX": 0.1, "AttachY": 0, "AttachZ": 0},
    {"ID": 2, "Name": "knee", "Type": "revolute", "Parent": 1, "AttachX": 0, "AttachY": -0.4, "AttachZ": 0},
    {"ID": 3, "Name": "ankle", "Type": "fixed", "Parent": 2, "AttachX": 0, "AttachY": -0.4, "AttachZ": 0},
]}, "BodyDefs": [{"Name": "ankle", "Shape": "box", "AttachX": 0.05, "AttachY": 0, "AttachZ": 0}]}  # fmt: skip
S = math.sqrt(0.5)


def test_deepmimic_hand_computed_fk(tmp_path):
    (tmp_path / "char_leg.txt").write_text(json.dumps(CHARACTER))
    # frame 0: root at (1, 2, 3) turned 90 deg about +Y (x -> -z), knee bent 90 deg about Z
    frames = [[0.05, 1, 2, 3, S, 0, S, 0, 1, 0, 0, 0, math.pi / 2], [0.05, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0]]
    (tmp_path / "leg_kick.txt").write_text(json.dumps({"Loop": "none", "Frames": frames}))
    motion = read_motion(tmp_path / "leg_kick.txt")
    assert motion.fps == 20.0 and motion.names == ["root", "hip", "knee", "ankle"]
    # the root's own attachment (0, 0, 7) is ignored. Frame 0: hip = root + Ry(90) (0.1, 0, 0);
    # knee 0.4 below; the knee's Rz(90) takes (0, -0.4, 0) to (0.4, 0, 0), Ry(90) to (0, 0, -0.4);
    # the ankle's end site (twice its box's attachment, (0.1, 0, 0)) to (0, 0.1, 0) by Rz(90)
    expected = [[[1, 2, 3], [1, 2, 2.9], [1, 1.6, 2.9], [1, 1.6, 2.5], [1, 1.7, 2.5]],
                [[0, 0, 0], [0.1, 0, 0], [0.1, -0.4, 0], [0.1, -0.8, 0], [0.2, -0.8, 0]]]  # fmt: skip
    np.testing.assert_allclose(motion.positions_with_end_sites(), expected, atol=1e-9)
    assert motion.end_site_names() == ["ankle_end"]

    frames[1] = frames[1][:-1]  # one value short
    (tmp_path / "leg_bad.txt").write_text(json.dumps({"Frames": frames}))
    with pytest.raises(UsageError, match=r"leg_bad.txt: frame 1 has 12 values, character char_leg.txt needs 13"):
        read_deepmimic(tmp_path / "leg_bad.txt")
    (tmp_path / "leg_nan.txt").write_text(json.dumps({"Frames": [[0.05] + [float("nan")] * 12]}))
    with pytest.raises(UsageError, match="non-finite"):
        read_deepmimic(tmp_path / "leg_nan.txt", character=tmp_path / "char_leg.txt")
    (tmp_path / "leg_cut.txt").write_text(json.dumps({"Frames": frames})[:40])
    with pytest.raises(UsageError, match="not valid JSON"):
        read_deepmimic(tmp_path / "leg_cut.txt")


def test_asf_amc_cmu(shared_motion):
    amc = shared_motion / "human/cmu/11_01.amc"
    motion = read_amc(amc)  # 11.asf beside it, 120 fps, CMU units
    frame_numbers = [line for line in amc.read_text().splitlines() if line.strip().isdigit()]
    assert motion.num_joints == 31 and len(motion) == len(frame_numbers) and motion.fps == 120.0
    assert motion.names[:3] == ["root", "lhipjoint", "lfemur"]
    # rest pose (head top included) as tall as the subject; in the same unit as the BVH
    # reader's CMU clips (other subjects): thigh bones within 15 %
    assert 1.5 < np.ptp(motion.rest_positions(end_sites=True)[:, 1]) < 1.9
    bvh = read_bvh(shared_motion / "human/cmu/02_01.bvh")  # CMU's scale detected from the rig
    assert np.allclose(bvh.offsets, read_bvh(shared_motion / "human/cmu/02_01.bvh", scale=CMU_SCALE).offsets)
    assert 1.3 < np.ptp(bvh.rest_positions(end_sites=True)[:, 1]) < 1.9
    thigh_asf = np.linalg.norm(motion.offsets[motion.names.index("ltibia")])
    thigh_bvh = np.linalg.norm(bvh.offsets[bvh.names.index("LeftLeg")])
    assert 0.85 < thigh_asf / thigh_bvh < 1.15 and 0.35 < thigh_asf < 0.5
    # frame 0 stands: feet at the floor, head 1.4-1.7 m up, knees bent forward (towards the toes)
    pos = motion.positions()
    i = {n: k for k, n in enumerate(motion.names)}
    assert pos[0, i["ltoes"], 1] < 0.12 and 1.4 < pos[0, i["head"], 1] < 1.7
    for side in "lr":
        hip, knee, ankle, toe = (pos[0, i[side + b]] for b in ("femur", "tibia", "foot", "toes"))
        forward = (toe - ankle) * [1, 0, 1]
        mid = (hip + ankle) / 2
        assert np.dot(knee - mid, forward) > 0


ASF = """\
:version 1.10
:name tiny
:units
  mass 1.0
  length 1.0
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name a
     direction 0 0 1
     length 1
     axis 0 0 90 XYZ
     dof rx
     limits (-180 180)
  end
  begin
     id 2
     name b
     direction 1 0 0
     length 2
     axis 0 0 0 XYZ
  end
:hierarchy
  begin
    root a
    a b
  end
"""
AMC = """\
:FULLY-SPECIFIED
:DEGREES
1
root 1 2 3 0 0 0
a 90
2
root 1 2 3 0 0 90
a 0
"""


def test_asf_amc_hand_computed_fk(tmp_path):
    (tmp_path / "07.asf").write_text(ASF)
    (tmp_path / "07_02.amc").write_text(AMC)
    motion = read_motion(tmp_path / "07_02.amc", scale=1.0, fps=30)
    assert motion.names == ["root", "a", "b"] and motion.parents == [-1, 0, 1] and motion.fps == 30.0
    # frame 1: a's C = Rz(90), so rx turns about C x = +Y: Ry(90) takes a's vector (0, 0, 1) to
    # (1, 0, 0) and b's (2, 0, 0) (b has no dof: it follows a) to (0, 0, -2).
    # frame 2: the root's Rz(90) alone: (0, 0, 1) stays, (2, 0, 0) -> (0, 2, 0).
    expected = [[[1, 2, 3], [1, 2, 3], [2, 2, 3], [2, 2, 1]], [[1, 2, 3], [1, 2, 3], [1, 2, 4], [1, 4, 4]]]
    np.testing.assert_allclose(motion.positions_with_end_sites(), expected, atol=1e-9)
    inches = read_amc(tmp_path / "07_02.amc")  # length 1.0: a unit is an inch
    np.testing.assert_allclose(inches.positions_with_end_sites(), np.array(expected) * 0.0254, atol=1e-9)

    (tmp_path / "07_03.amc").write_text(AMC.replace("a 0\n", "a 0 5\n"))
    with pytest.raises(UsageError, match=r"07_03.amc:8: a has 2 values, its dof needs 1"):
        read_amc(tmp_path / "07_03.amc")
    (tmp_path / "07_04.amc").write_text(AMC[: AMC.index("a 0")])
    with pytest.raises(UsageError, match="frame 2 lacks a"):
        read_amc(tmp_path / "07_04.amc")
    (tmp_path / "alone").mkdir()
    (tmp_path / "alone/09_01.amc").write_text(AMC)
    with pytest.raises(UsageError, match="no skeleton file 09.asf"):
        read_motion(tmp_path / "alone/09_01.amc")


def test_read_motion_dispatch(tmp_path, shared_motion):
    assert read_motion(shared_motion / "quadruped/mann_dog/D1_007_KAN01_001.bvh").num_joints == 21
    assert read_motion(shared_motion / "human/deepmimic/humanoid3d_jog.txt").num_joints == 15
    assert read_motion(shared_motion / "human/cmu/11_01.amc").num_joints == 31
    (tmp_path / "x.fbx").write_text("")
    with pytest.raises(UsageError, match="unknown motion format '.fbx'"):
        read_motion(tmp_path / "x.fbx")
    with pytest.raises(UsageError, match="character do not apply to .bvh"):
        read_motion(shared_motion / "quadruped/mann_dog/D1_007_KAN01_001.bvh", character="c.txt")
    with pytest.raises(UsageError, match="a character file"):
        read_motion(shared_motion / "human/deepmimic/char_humanoid3d.txt")


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2 * np.arccos(np.clip(np.abs((a * b).sum(-1)), 0, 1))


def test_resample_exact_at_integer_ratios(shared_motion):
    motion = read_bvh(shared_motion / "human/cmu/02_01.bvh")  # 120 fps
    down = motion.resample(20)
    assert down.fps == 20.0 and len(down) == (len(motion) - 1) // 6 + 1
    assert np.array_equal(down.rotations, motion.rotations[::6])
    assert np.array_equal(down.translations, motion.translations[::6])
    assert motion.resample(120) is motion

    bandai = read_bvh(next((shared_motion / "human/bandai1").glob("*.bvh")))  # 30 fps
    up = bandai.resample(60)
    assert len(up) == 2 * len(bandai) - 1
    assert (np.array_equal(up.rotations[::2], bandai.rotations)
            and np.array_equal(up.translations[::2], bandai.translations))
    # odd frames: halfway along the shorter arc, translations the mean
    a, mid, b = bandai.rotations[:-1], up.rotations[1::2], bandai.rotations[1:]
    np.testing.assert_allclose(_angle(a, mid), _angle(mid, b), atol=1e-6)
    np.testing.assert_allclose(up.translations[1::2], (bandai.translations[:-1] + bandai.translations[1:]) / 2)
    # 30 -> 20: output frame k lies at source frame 1.5 k, so even output frames are exact
    even = bandai.resample(20).rotations[::2]
    assert np.array_equal(even, bandai.rotations[::3][: len(even)])
    with pytest.raises(UsageError, match="cannot resample"):
        bandai.resample(0)


def test_rig_motion_is_the_bvh_output(shared_motion):
    motion = read_bvh(shared_motion / "quadruped/mann_dog/D1_007_KAN01_001.bvh")
    assert isinstance(motion, RigMotion) and motion.channels[0][:3] == ("Xposition", "Yposition", "Zposition")
    assert motion.end_site_names()[0] == "Head_end"
    half = motion.rescaled(0.5)
    np.testing.assert_allclose(half.positions(), motion.positions() * 0.5, atol=1e-9)
