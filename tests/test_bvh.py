"""BVH reader: real files from ../shared/data/motion, malformed files, and a hand-computed FK."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from omg.errors import UsageError
from omg.io.bvh import CMU_SCALE, BvhError, read_bvh

DATA = Path(__file__).parents[2] / "shared/data/motion"


def _data(pattern: str) -> Path:
    files = sorted(DATA.glob(pattern))
    if not files:
        pytest.skip(f"real motion data not found: {DATA / pattern} (see ../shared/data/motion/README.md)")
    return files[0]


def _declared_frames(path: Path) -> int:
    return int(re.search(r"Frames:\s*(\d+)", path.read_text()).group(1))


def _skeleton_facts(key: str) -> dict:
    return json.loads((DATA / "skeletons.json").read_text())[key]


def _check_bones_rigid(motion, positions: np.ndarray) -> None:
    """Bones without position channels keep their rest length in every frame."""
    for j, p in enumerate(motion.parents):
        if p < 0 or any(c.endswith("position") for c in motion.channels[j]):
            continue
        length = np.linalg.norm(positions[:, j] - positions[:, p], axis=-1)
        np.testing.assert_allclose(length, np.linalg.norm(motion.offsets[j]), atol=1e-6)


def _height(positions: np.ndarray) -> float:
    """Vertical extent of the joints in frame 0 (feet to head joint, no end sites)."""
    return float(np.ptp(positions[0, :, 1]))


def test_bandai_clip():
    path = _data("human/bandai1/*.bvh")
    motion = read_bvh(path)
    facts = _skeleton_facts("bandai_bvh")
    assert motion.names == facts["names"] and motion.parents == facts["parents"]
    assert motion.num_joints == 22 and len(motion) == _declared_frames(path) and motion.fps == 30.0
    assert all(len(c) == 6 for c in motion.channels)  # position channels on every joint
    positions = motion.positions()
    assert positions.shape == (len(motion), 22, 3)
    _check_bones_rigid(motion, positions)  # every joint has position channels, but they hold the offset:
    assert np.abs(motion.translations[:, 2:] - motion.offsets[2:]).max() < 1e-6
    assert 1.3 < _height(positions) < 2.0  # centimetres detected and converted to metres

    # the static joint_Root above the moving hips folds away, positions unchanged
    merged = motion.merge_root()
    assert merged.names[0] == "Hips" and merged.num_joints == 21 and merged.parents[0] == -1
    np.testing.assert_allclose(merged.positions(), positions[:, 1:], atol=1e-9)
    assert motion.to_clip().rotations is None  # hips translation is not a rigid bone
    clip = merged.to_clip("bandai", texts=["a person walks"])
    assert clip.rotations.shape == (len(motion), 21, 4) and clip.texts == ["a person walks"]


def test_cmu_clip():
    path = _data("human/cmu/*.bvh")
    motion = read_bvh(path, scale=CMU_SCALE)  # cgspeed files keep CMU's 1/0.45-inch unit
    assert motion.num_joints == 31 and len(motion) == _declared_frames(path) and motion.fps == 120.0
    assert motion.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    positions = motion.positions()
    _check_bones_rigid(motion, positions)
    assert 1.3 < _height(positions) < 2.0


def test_mann_dog_clip():
    path = _data("quadruped/mann_dog/*.bvh")
    motion = read_bvh(path)
    facts = _skeleton_facts("mann_dog_bvh")
    assert motion.names == facts["names"] and motion.parents == facts["parents"]
    assert motion.num_joints == 21 and len(motion) == _declared_frames(path) and motion.fps == 60.0
    positions = motion.positions()
    _check_bones_rigid(motion, positions)
    assert 0.3 < _height(positions) < 1.0  # a dog, in metres
    skeleton = motion.skeleton("mann_dog")
    assert skeleton.num_joints == 21 and skeleton.names[0] == "Hips"


HAND_WRITTEN = """\
HIERARCHY
ROOT hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation
  JOINT spine
  {
    OFFSET 0 20 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT head
    {
      OFFSET 0 10 0
      CHANNELS 3 Xposition Yposition Zposition
      End Site
      {
        OFFSET 0 5 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.04
100 50 0 90 0 0   90 90 0   0 30 0
0 0 0 0 0 0   0 0 0   0 10 0
"""


def test_hand_computed_fk(tmp_path):
    path = tmp_path / "three.bvh"
    path.write_text(HAND_WRITTEN)
    motion = read_bvh(path)  # rest pose 35 units tall: centimetres
    assert motion.names == ["hips", "spine", "head"] and motion.parents == [-1, 0, 1]
    assert motion.fps == 25.0 and len(motion) == 2
    np.testing.assert_allclose(motion.offsets, [[0, 0, 0], [0, 0.2, 0], [0, 0.1, 0]])
    assert motion.end_sites[0][0] == 2 and np.allclose(motion.end_sites[0][1], [0, 0.05, 0])
    # frame 0: hips at (1, 0.5, 0) turned 90 deg about Y, so the spine goes up 0.2 m. The
    # spine's R = Rz(90) Rx(90) (listed order) takes the head's channel offset (0, 0.3, 0)
    # to (0, 0, 0.3) (Rx), which Rz keeps and the hips' Ry(90) turns to (0.3, 0, 0).
    # Frame 1: rest pose at the origin, the head's channels restating its offset.
    expected = [[[1.0, 0.5, 0.0], [1.0, 0.7, 0.0], [1.3, 0.7, 0.0]], [[0, 0, 0], [0, 0.2, 0], [0, 0.3, 0]]]
    np.testing.assert_allclose(motion.positions(), expected, atol=1e-9)
    np.testing.assert_allclose(read_bvh(path, scale=1.0).positions(), np.array(expected) * 100, atol=1e-7)


def _corrupt(tmp_path, name: str, text: str) -> Path:
    path = tmp_path / f"{name}.bvh"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "name, edit, reason, line",
    [
        ("truncated", lambda t: t[: t.index("0 0 0 0 0 0   0 0 0")], "Frames: 2", 24),
        ("truncated_hierarchy", lambda t: t[: t.index("  JOINT spine")], "no MOTION", None),
        ("bad_number", lambda t: t.replace("100 50 0", "100 5x0 0"), "bad number '5x0'", 24),
        (
            "unknown_channel",
            lambda t: t.replace("Zrotation Xrotation Yrotation", "Zrotation Xrot Yrotation"),
            "Xrot",
            9,
        ),
        ("zero_frames", lambda t: t.replace("Frames: 2", "Frames: 0"), "zero frames", 22),
        ("wrong_count", lambda t: t.replace("0 0 0   0 10 0\n", "0 0 0   0 10\n"), "11 values", 25),
        ("nan", lambda t: t.replace("100 50 0", "100 nan 0"), "non-finite", 24),
        ("unclosed", lambda t: t.replace("}\nMOTION", "MOTION"), "hierarchy is complete", 20),
    ],
)
def test_malformed(tmp_path, name, edit, reason, line):
    path = _corrupt(tmp_path, name, edit(HAND_WRITTEN))
    with pytest.raises(BvhError) as info:
        read_bvh(path)
    message = str(info.value)
    assert isinstance(info.value, UsageError)
    assert str(path) in message and reason in message and "\n" not in message
    if line is not None:
        assert f"{path}:{line}:" in message


def test_missing_file(tmp_path):
    with pytest.raises(UsageError, match="nope.bvh: no such file"):
        read_bvh(tmp_path / "nope.bvh")
