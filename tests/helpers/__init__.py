"""Helpers the test modules share (no test module imports another): paths, the tiny DiT of the
plumbing tests, toy and walking clips, toy shard sets, BVH rigs, and an independent SMPL forward pass.
Topic helpers live in the submodules (``helpers.resume``, ``helpers.habit``, ...). ``tests/`` is on
``sys.path`` (pytest's rootdir-relative import of the test modules), so they import as ``helpers``."""

from __future__ import annotations

import io
import tarfile
from pathlib import Path

import numpy as np

from omg.data.shards import ShardWriter
from omg.motion import Clip, Representation
from omg.skeleton import SMPL22

REPO = Path(__file__).resolve().parents[2]
SHARED = REPO.parent / "shared"  # the real data beside the checkout
SHARED_MOTION = SHARED / "data" / "motion"
MINI = REPO / "shards" / "mini"  # the committed mini data

# The DiT of every test that checks plumbing rather than learning (checkpoints, resume, faults, the CLI):
# a step costs milliseconds; two blocks, so that per-block code (checkpointing, "blocks.1." keys) has a
# second block to get wrong. Tests of learning size their own models.
TINY_DIT = {"n_layers": 2, "d_model": 32, "n_heads": 2}
TINY_DIT_ARG = "--model.init_args.dit=" + str(TINY_DIT).replace("'", '"')  # the same, as an `omg fit` flag


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


def rewrite_member(shard: Path, key_ext: str, data: bytes) -> None:
    """Replace the payload of member ``key_ext`` (e.g. ``clip_0006.motion.npy``) in the tar ``shard``."""
    with tarfile.open(shard) as tar:
        members = [(m, tar.extractfile(m).read()) for m in tar.getmembers()]
    with tarfile.open(shard, "w") as tar:
        for m, payload in members:
            payload = data if m.name == key_ext else payload
            m.size = len(payload)
            tar.addfile(m, io.BytesIO(payload))


def scratch_registries(monkeypatch, *registries) -> None:
    """Let a test register into ``registries`` (omg.registry's) for its own length: omg's own entries are
    registered first, into the real entries (their modules' import may register into another registry, so
    all are loaded before any is copied), then each registry's entries are a copy that monkeypatch undoes."""
    for reg in registries:
        reg.names()
    for reg in registries:
        monkeypatch.setattr(reg, "_entries", dict(reg._entries))
