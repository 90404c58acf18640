"""Shared fixtures: the real-data folder, a toy representation and small shard sets."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from omg.data.shards import ShardWriter
from omg.motion import Clip, Representation
from omg.skeleton import SMPL22

REPO = Path(__file__).resolve().parents[1]
SHARED_MOTION = REPO.parent / "shared" / "data" / "motion"


# a two-joint BVH in centimetres: hips with position channels, a spine, one end site
TINY_BVH = """\
HIERARCHY
ROOT hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT spine
  {
    OFFSET 0 20 0
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


def rig_bvh(joints: list[tuple[str, str | None, tuple]], frames: int = 2, zero: bool = False) -> str:
    """A BVH text in centimetres of a rig given as (name, parent, offset) rows, parents first; leaf
    joints end in an end site half their bone; every frame is the rest pose (root at its offset).
    ``zero``: every OFFSET zero (a file without a rest pose)."""
    children = {name: [n for n, p, _ in joints if p == name] for name, _, _ in joints}
    offset = {name: np.zeros(3) if zero else np.array(off, float) for name, _, off in joints}
    lines = ["HIERARCHY"]

    def emit(name: str, depth: int) -> None:
        pad = "  " * depth
        chans = "6 Xposition Yposition Zposition Zrotation Xrotation Yrotation" if depth == 0 else \
            "3 Zrotation Xrotation Yrotation"
        lines.extend([f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {name}", f"{pad}{{",
                      f"{pad}  OFFSET {' '.join(map(str, offset[name]))}", f"{pad}  CHANNELS {chans}"])
        for c in children[name]:
            emit(c, depth + 1)
        if not children[name]:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {' '.join(map(str, offset[name] / 2))}",
                          f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(joints[0][0], 0)
    frame = " ".join(["0"] * (3 + 3 * len(joints)))
    return "\n".join(lines + ["MOTION", f"Frames: {frames}", "Frame Time: 0.05"] + [frame] * frames) + "\n"


def _sides(rows: list[tuple[str, str, tuple]], left: str, right: str, axis: int) -> list[tuple[str, str, tuple]]:
    """Rows written with ``{}`` for the side: left as given, right mirrored along ``axis``."""
    out = []
    for side, sign in ((left, 1.0), (right, -1.0)):
        for name, parent, off in rows:
            mirrored = tuple(v * sign if i == axis else v for i, v in enumerate(off))
            out.append((name.format(side), parent.format(side), mirrored))
    return out


# a Bandai-Namco-named human rig in a T-pose (cm, Y up, facing +Z, left = +X) and a MANN-named dog (cm)
BANDAI_RIG = [("joint_Root", None, (0, 0, 0)), ("Hips", "joint_Root", (0, 94, 0)), ("Spine", "Hips", (0, 10, 0)),
              ("Chest", "Spine", (0, 15, 0)), ("Neck", "Chest", (0, 20, 0)), ("Head", "Neck", (0, 10, 0))] + _sides([
    ("Shoulder_{}", "Chest", (3, 15, 0)), ("UpperArm_{}", "Shoulder_{}", (12, 0, 0)),
    ("LowerArm_{}", "UpperArm_{}", (28, 0, 0)), ("Hand_{}", "LowerArm_{}", (25, 0, 0)),
    ("UpperLeg_{}", "Hips", (9, -5, 0)), ("LowerLeg_{}", "UpperLeg_{}", (0, -42, 0)),
    ("Foot_{}", "LowerLeg_{}", (0, -40, 0)), ("Toes_{}", "Foot_{}", (0, -6, 13))], "L", "R", 0)
DOG_RIG = [("Hips", None, (0, 50, 0)), ("Spine", "Hips", (10, 0, 0)), ("Spine1", "Spine", (19, 0, 0)),
           ("Neck", "Spine1", (22, 0, 0)), ("Head", "Neck", (14, 5, 0)), ("Tail", "Hips", (-7, 0, 0)),
           ("Tail1", "Tail", (-15, 0, 0))] + _sides([
    ("{}Shoulder", "Spine1", (5, 0, 5)), ("{}Arm", "{}Shoulder", (0, -5, 0)), ("{}ForeArm", "{}Arm", (0, -20, 0)),
    ("{}Hand", "{}ForeArm", (0, -20, 0)), ("{}UpLeg", "Hips", (-5, 0, 5)), ("{}Leg", "{}UpLeg", (0, -20, 0)),
    ("{}Foot", "{}Leg", (0, -25, 0))], "Left", "Right", 2)


@pytest.fixture
def shared_motion() -> Path:
    if not (SHARED_MOTION / "manifest.json").exists():
        pytest.skip(f"real motion data not found at {SHARED_MOTION} (the shared/ folder beside the checkout)")
    return SHARED_MOTION


class JointPositions(Representation):
    """Flattened joint positions: the simplest representation, for data-layer tests."""

    name = "test-positions"

    @property
    def dim(self) -> int:
        return self.skeleton.num_joints * 3

    def encode(self, clip: Clip):
        return clip.positions.reshape(len(clip), -1).astype(np.float32), {}

    def decode(self, features, offsets=None):
        return features.reshape(*features.shape[:-1], -1, 3)


def toy_clip(index: int, frames: int | None = None, texts=None) -> Clip:
    rng = np.random.default_rng(index)
    T = frames or int(rng.integers(20, 80))
    positions = SMPL22.rest_positions()[None] + 0.01 * rng.standard_normal((T, 22, 3)).astype(np.float32)
    positions[:, :, 0] += index  # clip identity is readable from the data
    return Clip(id=f"clip.{index:04d}", skeleton=SMPL22, fps=20.0, positions=positions.astype(np.float32),
                texts=[f"caption {index}"] if texts is None else texts, category="human", source="test")


def write_toy_shards(out: Path, num_clips: int = 40, max_clips: int = 5) -> Path:
    ShardWriter(out, JointPositions(SMPL22), fps=20.0, max_clips=max_clips, log=lambda m: None).write(
        toy_clip(i) for i in range(num_clips)
    )
    return out


@pytest.fixture
def toy_shards(tmp_path) -> Path:
    return write_toy_shards(tmp_path / "toy")


# Tiny models: thread hand-offs cost more than they gain on a small shared CPU, and one thread
# keeps trained test models bit-reproducible. Set at import too, for module-scoped fixtures.
torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _quiet_threads():
    torch.set_num_threads(1)


def smpl_reference_joints(model: dict, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """Independent SMPL-family joints for the importer tests (scipy rotations, SMPL's parent chain), (T, 22, 3)
    in the body model's frame: ``model`` holds v_template, shapedirs and J_regressor."""
    from scipy.spatial.transform import Rotation

    from omg.skeleton import SMPL22_PARENTS

    n = len(betas)
    rest = (model["J_regressor"] @ (model["v_template"] + model["shapedirs"][..., :n] @ betas))[:22]
    out = np.zeros((len(poses), 22, 3))
    for t in range(len(poses)):
        G = [None] * 22
        for j in range(22):
            R = Rotation.from_rotvec(poses[t, 3 * j: 3 * j + 3])
            p = SMPL22_PARENTS[j]
            G[j] = R if p < 0 else G[p] * R
            out[t, j] = rest[0] + trans[t] if p < 0 else out[t, p] + G[p].apply(rest[j] - rest[p])
    return out


def walking_clip(index: int, fps: float = 20.0) -> Clip:
    """The rest pose gliding forward with jitter: enough structure for humanml3d263 and losses."""
    rng = np.random.default_rng(index)
    T = int(rng.integers(40, 100))
    positions = np.repeat(SMPL22.rest_positions()[None], T, axis=0)
    positions[:, :, 2] += np.linspace(0, rng.uniform(0, 3), T)[:, None]
    positions += 0.01 * rng.standard_normal(positions.shape)
    return Clip(id=f"walk{index}", skeleton=SMPL22, fps=fps, positions=positions.astype(np.float32),
                texts=["a person walks forward"], category="human", source="test")


@pytest.fixture(scope="session")
def h263_shards(tmp_path_factory) -> Path:
    """Small humanml3d263 train/val shard sets."""
    from omg.motion import get_representation

    out = tmp_path_factory.mktemp("h263")
    rep = get_representation("humanml3d263", SMPL22)
    ShardWriter(out / "train", rep, 20.0, max_clips=8, log=lambda m: None).write(walking_clip(i) for i in range(32))
    ShardWriter(out / "val", rep, 20.0, max_clips=8, log=lambda m: None).write(walking_clip(100 + i) for i in range(8))
    return out
