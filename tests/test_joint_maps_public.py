"""Built-in joint maps for public BVH rigs (LaFAN1, 100STYLE, Mixamo): registration, detection
(over look-alike maps such as CMU's) and retargeting a small walk in each naming onto smpl22."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from omg.io.read import read_motion
from omg.kinematics import ground_contacts
from omg.registry import JOINT_MAPS
from omg.retarget import detect_joint_map, get_joint_map, retarget

FPS = 30
FRAMES = 30
HIPS_CM = 95.0  # the root's height in the rest pose (centimetres, as the three datasets use)

# rig -> role names; "spine" lists the joints from the hips up to (not including) the neck,
# the collars branch from the last one
RIGS = {
    "lafan1": dict(
        hips="Hips", spine=["Spine", "Spine1", "Spine2"], neck="Neck", head="Head",
        collar="{}Shoulder", arm="{}Arm", forearm="{}ForeArm", hand="{}Hand",
        upleg="{}UpLeg", leg="{}Leg", foot="{}Foot", toe="{}Toe",
    ),
    "style100": dict(
        hips="Hips", spine=["Chest", "Chest2", "Chest3", "Chest4"], neck="Neck", head="Head",
        collar="{}Collar", arm="{}Shoulder", forearm="{}Elbow", hand="{}Wrist",
        upleg="{}Hip", leg="{}Knee", foot="{}Ankle", toe="{}Toe",
    ),
    "mixamo": dict(
        hips="mixamorig:Hips", spine=["mixamorig:Spine", "mixamorig:Spine1", "mixamorig:Spine2"],
        neck="mixamorig:Neck", head="mixamorig:Head",
        collar="mixamorig:{}Shoulder", arm="mixamorig:{}Arm", forearm="mixamorig:{}ForeArm",
        hand="mixamorig:{}Hand", upleg="mixamorig:{}UpLeg", leg="mixamorig:{}Leg",
        foot="mixamorig:{}Foot", toe="mixamorig:{}ToeBase",
    ),
}  # fmt: skip


def _hierarchy(rig: dict) -> list[tuple[str, str | None, tuple, bool]]:
    """(name, parent, offset in cm, has an end site) in depth-first order: a T-pose facing +Z,
    left = +X, Y up."""
    joints = [(rig["hips"], None, (0.0, 0.0, 0.0), False)]
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        chain = [(rig["upleg"], (9 * sx, -6, 0)), (rig["leg"], (0, -42, 0)), (rig["foot"], (0, -40, 0)),
                 (rig["toe"], (0, -6, 13))]  # fmt: skip
        parent = rig["hips"]
        for i, (role, off) in enumerate(chain):
            joints.append((role.format(side), parent, off, i == len(chain) - 1))
            parent = role.format(side)
    seg = 50.0 / (len(rig["spine"]) + 1)  # hips -> neck: 50 cm
    parent = rig["hips"]
    for name in rig["spine"]:
        joints.append((name, parent, (0, seg, 0), False))
        parent = name
    chest = parent
    joints += [(rig["neck"], chest, (0, seg, 0), False), (rig["head"], rig["neck"], (0, 12, 0), True)]
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        chain = [(rig["collar"], (3 * sx, 0.7 * seg, 0)), (rig["arm"], (15 * sx, 0, 0)),
                 (rig["forearm"], (28 * sx, 0, 0)), (rig["hand"], (25 * sx, 0, 0))]  # fmt: skip
        parent = chest
        for i, (role, off) in enumerate(chain):
            joints.append((role.format(side), parent, off, i == len(chain) - 1))
            parent = role.format(side)
    return joints


def _angles(rig: dict, t: int) -> dict:
    """(z, x, y) degrees per joint at frame t: legs swinging in antiphase (one step per half
    second), the swinging leg's knee bent, arms lowered and swinging against the legs."""
    phase = 2 * math.pi * t / FPS  # one stride (two steps) per second
    out = {}
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        swing = sign * 20.0 * math.sin(phase)  # about X: > 0 takes the foot back (-Z)
        out[rig["upleg"].format(side)] = (0.0, swing, 0.0)
        # the knee bends while the leg swings forward (its hip angle decreasing)
        bend = 35.0 * max(0.0, -sign * math.cos(phase))
        out[rig["leg"].format(side)] = (0.0, bend, 0.0)
        out[rig["arm"].format(side)] = (-sign * 75.0, -0.5 * swing, 0.0)
    return out


def _write(path: Path, rig: dict, root_y: np.ndarray, root_z: np.ndarray) -> None:
    joints = _hierarchy(rig)
    children: dict = {}
    for name, parent, _, _ in joints:
        children.setdefault(parent, []).append(name)
    info = {name: (off, end) for name, _, off, end in joints}
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "  " * depth
        off, end = info[name]
        root = depth == 0
        lines.extend([f"{pad}{'ROOT' if root else 'JOINT'} {name}", f"{pad}{{",
                      f"{pad}  OFFSET {off[0]:.4f} {off[1]:.4f} {off[2]:.4f}",
                      f"{pad}  CHANNELS " + ("6 Xposition Yposition Zposition " if root else "3 ")
                      + "Zrotation Xrotation Yrotation"])  # fmt: skip
        for child in children.get(name, []):
            emit(child, depth + 1)
        if end:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET 0 0 5", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(rig["hips"], 0)
    order = []
    stack = [rig["hips"]]
    while stack:  # depth first, as emitted
        name = stack.pop()
        order.append(name)
        stack.extend(reversed(children.get(name, [])))
    lines += ["MOTION", f"Frames: {FRAMES}", f"Frame Time: {1.0 / FPS:.8f}"]
    for t in range(FRAMES):
        angles = _angles(rig, t)
        row = [0.0, float(root_y[t]), float(root_z[t])]
        for name in order:
            row.extend(angles.get(name, (0.0, 0.0, 0.0)))
        lines.append(" ".join(f"{v:.5f}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def _walk_bvh(tmp_path: Path, name: str) -> Path:
    """The rig's walk along +Z, its root moved so that the stance foot stays planted: the hips
    bob to keep the lower foot 2 cm above y = 0 and travel as far as that foot swings back."""
    rig, path = RIGS[name], tmp_path / f"{name}_walk.bvh"
    _write(path, rig, np.full(FRAMES, HIPS_CM), np.zeros(FRAMES))  # walking on the spot
    motion = read_motion(path)
    feet = np.array([[motion.names.index(rig[r].format(s)) for r in ("foot", "toe")] for s in ("Left", "Right")])
    P = motion.positions() * 100.0  # cm
    lowest = P[:, feet, 1].min(2)  # (T, 2): each leg's lower foot joint
    stance = lowest.argmin(1)  # (T,) the leg on the ground
    toe_z = P[:, feet[:, 1], 2]  # (T, 2)
    step = -(toe_z[1:, stance[:-1]].diagonal() - toe_z[:-1, stance[:-1]].diagonal())  # root advance
    _write(path, rig, HIPS_CM - (lowest.min(1) - 2.0), np.concatenate([[0.0], np.cumsum(step)]))
    return path


def test_public_maps_are_registered():
    assert {"lafan1", "style100", "mixamo"} <= set(JOINT_MAPS.names())
    for name in ("lafan1", "style100", "mixamo"):
        jmap = get_joint_map(name)
        assert jmap.name == name and jmap.target == "smpl22" and jmap.category == "human"
        assert len(jmap.joints) == 22
    assert "100STYLE" in JOINT_MAPS.describe("style100")
    assert "LaFAN1" in JOINT_MAPS.describe("lafan1") and "Mixamo" in JOINT_MAPS.describe("mixamo")


@pytest.mark.parametrize("name", sorted(RIGS))
def test_public_rig_detected_and_retargeted(tmp_path, name):
    motion = read_motion(_walk_bvh(tmp_path, name))
    assert RIGS[name]["hips"] in motion.names  # Mixamo's "mixamorig:" prefix survives the reader
    assert len(motion) == FRAMES and motion.fps == FPS
    assert detect_joint_map(motion).name == name
    assert detect_joint_map(motion, "smpl22").name == name
    if name == "lafan1":  # MotionBuilder-like names, but CMU's map needs Neck1 and LeftToeBase
        assert get_joint_map("cmu").missing(motion.names)
    if name == "style100":  # CMU 3dsMax's map fits too; the map explaining more joints wins
        assert not get_joint_map("cmu_3dsmax").missing(motion.names)

    clip = retarget(motion, "smpl22", fps=20)
    P, skel = clip.positions, clip.skeleton
    assert skel.name == "smpl22" and clip.category == "human" and np.isfinite(P).all()
    bones = np.stack([np.linalg.norm(P[:, j] - P[:, p], axis=-1) for j, p in enumerate(skel.parents) if p >= 0], 1)
    assert np.ptp(bones, 0).max() < 1e-3  # constant bone lengths (metres)
    feet = P[:, list(skel.feet), 1]
    assert abs(feet.min()) < 0.02  # the lowest foot joint touches the floor
    contact = ground_contacts(torch.from_numpy(P).double(), skel.feet, clip.fps).numpy()
    assert contact[:, [1, 3]].any(0).all()  # both feet plant (skel.feet: ankle, foot, ankle, foot)
    assert 0.85 < np.median(P[:, 0, 1]) < 1.05  # the pelvis where the rig's hips are
    # left is left: the left hip lies at +X of the right one while walking along +Z
    assert (P[:, skel.names.index("left_hip"), 0] > P[:, skel.names.index("right_hip"), 0]).all()
    assert P[-1, 0, 2] - P[0, 0, 2] > 0.5
