"""omg.kinematics: Kabsch, IK <-> FK on a real BVH, HumanML3D's foot-contact rule; joint maps
registered by a plugin are found by detection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers import scratch_registries
from omg.io.read import read_motion
from omg.kinematics import (
    FOOT_CONTACT_SPEED,
    clip_offsets,
    foot_contacts,
    ground_contacts,
    kabsch,
    nearest_rotation,
    positions_to_rotations,
)
from omg.registry import JOINT_MAPS
from omg.retarget import JointMap, detect_joint_map, get_joint_map, retarget
from omg.rotations import axis_angle_to_quat, quat_to_matrix


def _rotations(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return quat_to_matrix(axis_angle_to_quat(2.0 * torch.randn(n, 3, generator=g, dtype=torch.float64)))


def test_kabsch_recovers_a_known_rotation():
    g = torch.Generator().manual_seed(1)
    R = _rotations(5)  # (5, 3, 3)
    rest = torch.randn(4, 3, generator=g, dtype=torch.float64)  # (C, 3), broadcast over the batch
    observed = rest @ R.transpose(-1, -2)  # (5, C, 3): R rest_c
    torch.testing.assert_close(kabsch(rest, observed), R)
    # weights: noise on a vector of weight ~0 does not matter
    noisy = observed.clone()
    noisy[:, 0] += 0.5
    weights = torch.tensor([1e-12, 1.0, 1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(kabsch(rest, noisy, weights), R, atol=1e-6, rtol=0)
    # two vectors (coplanar: the third singular value is 0): still the rotation, not a reflection
    torch.testing.assert_close(kabsch(rest[:2], observed[:, :2]), R)


def test_kabsch_returns_a_rotation_where_the_best_fit_is_a_reflection():
    rest = torch.eye(3, dtype=torch.float64)  # the axes
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    observed = rest @ mirror  # z flipped: only a reflection maps them exactly
    R = kabsch(rest, observed)
    assert torch.linalg.det(R) == pytest.approx(1.0)
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64))
    # the best rotation keeps the two axes it can (x, y) and gives up on z
    torch.testing.assert_close(rest[:2] @ R.T, observed[:2])


def test_nearest_rotation_is_the_rotation_itself_and_the_mean_of_a_symmetric_spread():
    R = _rotations(4)  # (4, 3, 3)
    torch.testing.assert_close(nearest_rotation(R), R)
    # a rotation scaled and sheared a little: its polar factor, not its transpose
    g = torch.Generator().manual_seed(2)
    bent = 1.3 * R + 0.05 * torch.randn(4, 3, 3, generator=g, dtype=torch.float64)
    near = nearest_rotation(bent)
    torch.testing.assert_close(near @ near.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))
    assert (torch.linalg.det(near) - 1).abs().max() < 1e-12
    assert ((near - R).norm(dim=(-2, -1)) < 0.1).all() and ((near.transpose(-1, -2) - R).norm(dim=(-2, -1)) > 0.5).all()
    # the matrix mean of R turned +-40 degrees about one axis is no rotation; the nearest one is R
    turns = quat_to_matrix(axis_angle_to_quat(torch.tensor([[0.0, 0.0, 0.7], [0.0, 0.0, -0.7]], dtype=torch.float64)))
    torch.testing.assert_close(nearest_rotation((R[0] @ turns).mean(0)), R[0])


@pytest.fixture
def bvh_motion(shared_motion):
    """A Bandai-Namco walk with its static root folded into the hips: constant bone offsets."""
    return read_motion(min((shared_motion / "human/bandai1").glob("*walk_normal*.bvh"))).merge_root()


@pytest.mark.parametrize("aim_from_fk", [True, False])
def test_ik_then_fk_reproduces_a_real_bvh(bvh_motion, aim_from_fk):
    skel = bvh_motion.skeleton()  # the file's own rig: several joints with several children
    assert sum(len(skel.children(j)) > 1 for j in range(skel.num_joints)) >= 2
    positions = torch.from_numpy(bvh_motion.positions())  # (T, J, 3)
    offsets = torch.from_numpy(bvh_motion.offsets)
    rotations = positions_to_rotations(skel, positions, offsets, aim_from_fk=aim_from_fk)
    assert rotations.shape == (*positions.shape[:-1], 4)
    fk = skel.forward_kinematics(rotations, positions[:, 0], offsets)
    torch.testing.assert_close(fk, positions, atol=1e-6, rtol=0)
    # the clip's own bones (clip_offsets) reproduce it too
    own = clip_offsets(skel, positions)
    fk = skel.forward_kinematics(positions_to_rotations(skel, positions, own), positions[:, 0], own)
    torch.testing.assert_close(fk, positions, atol=1e-4, rtol=0)


def test_ik_leaves_joints_not_placed_rigid(bvh_motion):
    skel = bvh_motion.skeleton()
    positions = torch.from_numpy(bvh_motion.positions())
    offsets = torch.from_numpy(bvh_motion.offsets)
    hand = bvh_motion.names.index("Hand_L")
    placed = [j != hand for j in range(skel.num_joints)]
    rotations = positions_to_rotations(skel, positions, offsets, placed=placed)
    elbow = skel.parents[hand]  # its only child is the hand: nothing to aim at
    identity = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(len(positions), 4)
    torch.testing.assert_close(rotations[:, elbow], identity)


def test_foot_contacts_by_hand():
    """Two feet at 20 fps: HumanML3D's rule is a step under sqrt(0.002) m ≈ 4.47 cm per frame."""
    fps = 20.0
    assert FOOT_CONTACT_SPEED == pytest.approx(math.sqrt(0.002) * 20)
    steps = torch.tensor([[0.00, 0.10], [0.01, 0.05], [0.04, 0.04], [0.046, 0.0], [0.2, 0.0]], dtype=torch.float64)
    T = len(steps) + 1
    positions = torch.zeros(T, 3, 3, dtype=torch.float64)  # joints: 0 = pelvis, 1 and 2 = feet
    positions[1:, 1, 0] = steps[:, 0].cumsum(0)  # foot 1 moves along x
    positions[1:, 2, 2] = steps[:, 1].cumsum(0)  # foot 2 along z
    positions[:, 0, 0] = torch.arange(T) * 1.0  # the pelvis runs: not a foot, not counted
    contacts = foot_contacts(positions, (1, 2), fps)
    expected = torch.tensor([[True, False], [True, False], [True, True], [False, True], [False, True]])
    assert contacts.shape == (T - 1, 2) and torch.equal(contacts, expected)
    assert int(contacts.sum()) == 6
    # the same speed at another frame rate: half the step per frame at 40 fps
    assert torch.equal(foot_contacts(positions / 2, (1, 2), 40.0), expected)
    # leading batch dims
    assert torch.equal(foot_contacts(positions.expand(3, -1, -1, -1), [1, 2], fps), expected.expand(3, -1, -1))


def test_ground_contacts_need_slow_and_low():
    fps = 20.0
    T = 6
    positions = torch.zeros(T, 2, 3, dtype=torch.float64)
    positions[:, 1, 1] = torch.tensor([0.0, 0.0, 0.3, 0.3, 0.0, 0.0])  # foot lifted 30 cm on frames 2-3
    contacts = ground_contacts(positions, (0, 1), fps)
    assert contacts.shape == (T, 2)
    assert contacts[:, 0].all()  # still on the floor
    # foot 1: slow towards the next frame and low; the last frame repeats the one before
    assert contacts[:, 1].tolist() == [True, False, False, False, True, True]


def _renamed_bvh(src, dst, rename: dict) -> None:
    text = src.read_text()
    for old, new in rename.items():
        text = text.replace(f"JOINT {old}\n", f"JOINT {new}\n").replace(f"ROOT {old}\n", f"ROOT {new}\n")
    dst.write_text(text)


@pytest.fixture
def plugin_registry(monkeypatch):
    """JOINT_MAPS with its built-ins loaded; what a test registers is gone afterwards."""
    scratch_registries(monkeypatch, JOINT_MAPS)
    return JOINT_MAPS


def test_builtin_joint_maps_are_registered_files():
    assert {"bandai", "cmu", "cmu_3dsmax", "cmu_asf", "deepmimic_humanoid", "mann_dog", "deepmimic_dog"} <= set(
        JOINT_MAPS.names()
    )
    assert JOINT_MAPS.get("bandai").suffix == ".yaml" and JOINT_MAPS.get("bandai").is_file()
    bandai = get_joint_map("bandai")
    assert bandai.name == "bandai" and bandai.target == "smpl22" and bandai.category == "human"
    assert bandai.joints["right_hip"] == "UpperLeg_R" and len(bandai.joints) == 21
    assert get_joint_map("mann_dog").category == "dog"


@pytest.mark.parametrize("as_file", [True, False])
def test_plugin_joint_map_is_found_by_detection(shared_motion, tmp_path, plugin_registry, as_file):
    src = min((shared_motion / "human/bandai1").glob("*walk_normal*.bvh"))
    bandai = get_joint_map("bandai")
    rename = {name: f"my_{name}" for name in set(bandai.joints.values())}
    _renamed_bvh(src, tmp_path / "renamed.bvh", rename)
    renamed = read_motion(tmp_path / "renamed.bvh")
    assert detect_joint_map(renamed) is None
    joints = {t: rename[s] for t, s in bandai.joints.items()}
    if as_file:
        lines = ["target: smpl22", "joints:"] + [f"  {t}: {s}" for t, s in joints.items()]
        (tmp_path / "rig.yaml").write_text("\n".join(lines) + "\n")
        plugin_registry.register("my_rig", tmp_path / "rig.yaml")
    else:
        plugin_registry.register("my_rig", JointMap("my_rig", "smpl22", joints))
    found = detect_joint_map(renamed)
    assert found is not None and found.name == "my_rig" and detect_joint_map(renamed, "smpl22") == found
    assert get_joint_map("my_rig") == found
    assert detect_joint_map(read_motion(src)).name == "bandai"  # the built-ins still fit their rigs
    mine, builtin = retarget(renamed, "smpl22", fps=20), retarget(read_motion(src), "smpl22", fps=20)
    np.testing.assert_allclose(mine.positions, builtin.positions, atol=1e-6)
    assert mine.category == "human"
