"""Skeleton facts (SMPL-22, SMAL-35 exactly as in DESIGN.md), rest poses, and hand-checked forward kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omg.registry import SKELETONS
from omg.rotations import axis_angle_to_quat, quat_identity, quat_mul, quat_to_matrix
from omg.skeleton import SMAL35, SMPL22, Skeleton, get_skeleton

F64 = torch.float64

# ---------------------------------------------------------------------------------------------
# facts copied literally from DESIGN.md, "Skeletons (facts to use exactly)"

SMPL22_NAMES = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
]  # fmt: skip
SMPL22_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
SMPL22_CHAINS = [[0, 2, 5, 8, 11], [0, 1, 4, 7, 10], [0, 3, 6, 9, 12, 15], [9, 14, 17, 19, 21], [9, 13, 16, 18, 20]]
SMPL22_FACE = [2, 1, 17, 16]
SMPL22_FEET_L, SMPL22_FEET_R = [7, 10], [8, 11]
SMPL22_PRIMAL = [0, 10, 11, 15, 20, 21, 9]
SMPL22_END_EFFECTORS = [11, 10, 15, 21, 20]

SMAL35_NAMES = [
    "pelvis", "pelvis0", "spine", "spine0", "spine1", "spine2", "spine3", "LLeg1", "LLeg2",
    "LLeg3", "LFoot", "RLeg1", "RLeg2", "RLeg3", "RFoot", "Neck", "Head", "LLegBack1",
    "LLegBack2", "LLegBack3", "LFootBack", "RLegBack1", "RLegBack2", "RLegBack3", "RFootBack",
    "Tail1", "Tail2", "Tail3", "Tail4", "Tail5", "Tail6", "Tail7", "Mouth", "LEar", "REar",
]  # fmt: skip
SMAL35_PARENTS = [-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 6, 11, 12, 13, 6, 15, 0, 17, 18, 19, 0, 21, 22, 23, 0, 25, 26,
                  27, 28, 29, 30, 16, 16, 16]  # fmt: skip
SMAL35_CHAINS = [[0, 1, 2, 3, 4, 5, 6, 15, 16, 32], [6, 7, 8, 9, 10], [6, 11, 12, 13, 14], [0, 17, 18, 19, 20],
                 [0, 21, 22, 23, 24], [0, 25, 26, 27, 28, 29, 30, 31], [16, 33], [16, 34]]  # fmt: skip
SMAL35_FACE = [11, 7, 21, 17]
SMAL35_PRIMAL = [0, 20, 24, 16, 10, 14, 6]
SMAL35_END_EFFECTORS = [24, 20, 16, 14, 10]
SMAL35_SYMMETRY = [0, 1, 2, 3, 4, 5, 6, 11, 12, 13, 14, 7, 8, 9, 10, 15, 16, 21, 22, 23, 24, 17, 18, 19, 20, 25, 26,
                   27, 28, 29, 30, 31, 32, 34, 33]  # fmt: skip


# ---------------------------------------------------------------------------------------------
# helpers


def mirror_name(name: str) -> str:
    """left_x <-> right_x (SMPL) and Lx <-> Rx (SMAL); centre joints are their own mirror."""
    for a, b in (("left_", "right_"), ("right_", "left_")):
        if name.startswith(a):
            return b + name[len(a):]
    if len(name) > 1 and name[0] in "LR" and name[1].isupper():
        return {"L": "R", "R": "L"}[name[0]] + name[1:]
    return name


def about(axis: str, degrees: float) -> torch.Tensor:
    """Quaternion for a rotation about a coordinate axis (float64)."""
    aa = torch.zeros(3, dtype=F64)
    aa["xyz".index(axis)] = math.radians(degrees)
    return axis_angle_to_quat(aa)


def identity_pose(skel: Skeleton, *batch: int) -> torch.Tensor:
    return quat_identity((*batch, skel.num_joints), dtype=F64)


def lists(groups) -> list:
    return [list(g) for g in groups]


# ---------------------------------------------------------------------------------------------
# the facts


def test_smpl22_facts():
    s = SMPL22
    assert s.name == "smpl22" and s.num_joints == 22
    assert list(s.names) == SMPL22_NAMES
    assert list(s.parents) == SMPL22_PARENTS
    assert lists(s.chains) == SMPL22_CHAINS
    assert list(s.face_joints) == SMPL22_FACE
    assert list(s.feet_left) == SMPL22_FEET_L and list(s.feet_right) == SMPL22_FEET_R
    assert list(s.feet) == SMPL22_FEET_L + SMPL22_FEET_R
    assert list(s.primal_joints) == SMPL22_PRIMAL
    assert list(s.end_effectors) == SMPL22_END_EFFECTORS
    # face joints are (r_hip, l_hip, r_shoulder, l_shoulder)
    assert [s.names[j] for j in s.face_joints] == ["right_hip", "left_hip", "right_shoulder", "left_shoulder"]


def test_smal35_facts():
    s = SMAL35
    assert s.name == "smal35" and s.num_joints == 35
    assert list(s.names) == SMAL35_NAMES
    assert list(s.parents) == SMAL35_PARENTS
    assert lists(s.chains) == SMAL35_CHAINS
    assert list(s.face_joints) == SMAL35_FACE
    assert list(s.primal_joints) == SMAL35_PRIMAL
    assert list(s.end_effectors) == SMAL35_END_EFFECTORS
    assert list(s.symmetry) == SMAL35_SYMMETRY
    assert [s.names[j] for j in s.face_joints] == ["RLeg1", "LLeg1", "RLegBack1", "LLegBack1"]
    # feet are the four paws, left ones on the left
    assert {s.names[j] for j in s.feet_left} == {"LFoot", "LFootBack"}
    assert {s.names[j] for j in s.feet_right} == {"RFoot", "RFootBack"}


def test_primal_joints_correspond_between_human_and_animal():
    """Position k matches: hind legs <-> human legs, front legs <-> human arms, head <-> head."""
    human = [SMPL22.names[j] for j in SMPL22.primal_joints]
    animal = [SMAL35.names[j] for j in SMAL35.primal_joints]
    assert list(zip(human, animal)) == [
        ("pelvis", "pelvis"), ("left_foot", "LFootBack"), ("right_foot", "RFootBack"), ("head", "Head"),
        ("left_wrist", "LFoot"), ("right_wrist", "RFoot"), ("spine3", "spine3"),
    ]


@pytest.mark.parametrize("skel", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_chains_follow_parents(skel):
    for chain in skel.chains:
        for parent, child in zip(chain, chain[1:]):
            assert skel.parents[child] == parent, (chain, child)


@pytest.mark.parametrize("skel", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_symmetry_is_an_involution_mapping_left_to_right(skel):
    sym = skel.symmetry
    assert len(sym) == skel.num_joints
    assert [sym[sym[j]] for j in range(skel.num_joints)] == list(range(skel.num_joints))
    for j, name in enumerate(skel.names):
        assert skel.names[sym[j]] == mirror_name(name), (name, skel.names[sym[j]])
    # mirrored joints share a parent's mirror
    for j, p in enumerate(skel.parents):
        if p >= 0:
            assert skel.parents[sym[j]] == sym[p]


@pytest.mark.parametrize("skel", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_registered_by_name(skel):
    assert skel.name in SKELETONS
    assert SKELETONS.get(skel.name) is skel
    assert get_skeleton(skel.name) is skel and get_skeleton(skel) is skel


def test_index_and_children():
    assert SMPL22.index("left_wrist") == 20
    assert SMPL22.children(9) == [12, 13, 14]
    assert SMAL35.children(16) == [32, 33, 34]
    with pytest.raises(KeyError, match="tail"):
        SMPL22.index("tail")


# ---------------------------------------------------------------------------------------------
# rest poses


def test_smpl22_rest_pose_faces_plus_z_with_left_plus_x():
    pos = SMPL22.rest_positions()
    n = {name: pos[j] for j, name in enumerate(SMPL22.names)}
    for side in ("hip", "shoulder", "knee", "ankle", "foot", "wrist"):
        assert n[f"left_{side}"][0] > 0 > n[f"right_{side}"][0], side
    # HumanML3D's facing: forward = up x across, across = (r_hip - l_hip) + (r_shoulder - l_shoulder)
    r_hip, l_hip, r_sho, l_sho = (pos[j] for j in SMPL22.face_joints)
    across = (r_hip - l_hip) + (r_sho - l_sho)
    forward = np.cross([0.0, 1.0, 0.0], across)
    forward /= np.linalg.norm(forward)
    assert forward @ np.array([0.0, 0.0, 1.0]) > 0.99
    # toes in front of the ankles
    assert n["left_foot"][2] > n["left_ankle"][2] and n["right_foot"][2] > n["right_ankle"][2]


def test_smpl22_rest_pose_stands_on_the_floor():
    pos = SMPL22.rest_positions()
    feet_y = pos[list(SMPL22.feet), 1]
    assert pos[:, 1].min() == pytest.approx(feet_y.min())
    assert -0.01 <= feet_y.min() < 0.05
    assert 1.5 <= pos[SMPL22.index("head"), 1] <= 1.9
    assert 1.5 <= pos[:, 1].max() <= 1.9
    assert pos[SMPL22.index("head"), 1] > pos[SMPL22.index("neck"), 1] > pos[0, 1] > pos[SMPL22.index("left_knee"), 1]


def test_smal35_rest_pose_legs_below_spine_paws_on_floor():
    pos = SMAL35.rest_positions()
    spine = [SMAL35.index(n) for n in ("pelvis", "pelvis0", "spine", "spine0", "spine1", "spine2", "spine3")]
    legs = [j for j, n in enumerate(SMAL35.names) if "Leg" in n or "Foot" in n]
    assert len(legs) == 16
    assert pos[legs, 1].max() < pos[spine, 1].min()
    paws = list(SMAL35.feet)
    assert np.all(np.abs(pos[paws, 1]) < 0.05)
    assert pos[:, 1].min() > -0.01
    # faces +Z, left +X
    assert pos[SMAL35.index("Head"), 2] > pos[0, 2] > pos[SMAL35.index("Tail7"), 2]
    for j, name in enumerate(SMAL35.names):
        if mirror_name(name) != name:
            assert (pos[j, 0] > 0) == name.startswith("L"), name


@pytest.mark.parametrize("skel", [SMPL22, SMAL35], ids=lambda s: s.name)
def test_fk_with_identity_rotations_is_the_rest_pose(skel):
    root = torch.as_tensor(skel.rest_offsets[0], dtype=F64)
    pos = skel.forward_kinematics(identity_pose(skel), root)
    np.testing.assert_allclose(pos.numpy(), skel.rest_positions(), atol=1e-6)
    # and in a batch, shifted by the root
    shift = torch.tensor([1.0, 0.0, -2.0], dtype=F64)
    batched = skel.forward_kinematics(identity_pose(skel, 2, 3), (root + shift).expand(2, 3, 3))
    assert batched.shape == (2, 3, skel.num_joints, 3)
    np.testing.assert_allclose(batched[1, 2].numpy(), skel.rest_positions() + shift.numpy(), atol=1e-6)


# ---------------------------------------------------------------------------------------------
# forward kinematics against hand-computed poses

# root -> j1 -> j2 -> j3, and j4 branching off j1
CHAIN_PARENTS = [-1, 0, 1, 2, 1]
CHAIN_OFFSETS = np.array([[5.0, 6.0, 7.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0], [0.0, 0.0, 1.0]])


def chain() -> Skeleton:
    return Skeleton.from_parents("chain", CHAIN_PARENTS, CHAIN_OFFSETS)


def chain_pose() -> torch.Tensor:
    """90 deg about Z at the root, 90 deg about X at j1, identity at j2, 30 deg about Y at the leaves."""
    return torch.stack((about("z", 90), about("x", 90), about("x", 0), about("y", 30), about("y", 30)))


ROOT = torch.tensor([10.0, 20.0, 30.0], dtype=F64)
# By hand: G0 = Rz90, G1 = Rz90 @ Rx90 = [[0,0,1],[1,0,0],[0,1,0]], G2 = G1
#   p1 = p0 + Rz90 (1,0,0)  = p0 + (0,1,0)
#   p2 = p1 + G1 (0,2,0)    = p1 + (0,0,2)
#   p3 = p2 + G2 (0,0,3)    = p2 + (3,0,0)
#   p4 = p1 + G1 (0,0,1)    = p1 + (1,0,0)
CHAIN_EXPECTED = [[10, 20, 30], [10, 21, 30], [10, 21, 32], [13, 21, 32], [11, 21, 30]]


def test_fk_hand_computed_chain():
    pos = chain().forward_kinematics(chain_pose(), ROOT)
    torch.testing.assert_close(pos, torch.tensor(CHAIN_EXPECTED, dtype=F64), atol=1e-12, rtol=0)


def test_fk_hand_computed_half_turn():
    """Half a turn about Y at the root mirrors x and z of every offset."""
    pose = identity_pose(chain())
    pose[0] = about("y", 180)
    pos = chain().forward_kinematics(pose, torch.zeros(3, dtype=F64))
    expected = [[0, 0, 0], [-1, 0, 0], [-1, 2, 0], [-1, 2, -3], [-1, 0, -1]]
    torch.testing.assert_close(pos, torch.tensor(expected, dtype=F64), atol=1e-12, rtol=0)


def test_global_rotations_hand_computed():
    g = chain().global_rotations(chain_pose())
    assert g.shape == (5, 4)
    G1 = torch.tensor([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=F64)
    Rz90 = torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=F64)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    Ry30 = torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=F64)
    expected = torch.stack((Rz90, G1, G1, G1 @ Ry30, G1 @ Ry30))
    torch.testing.assert_close(quat_to_matrix(g), expected, atol=1e-12, rtol=0)


def test_fk_batched_matches_per_sample():
    skel = chain()
    g = torch.Generator().manual_seed(0)
    B, T, J = 2, 3, skel.num_joints
    rot = torch.randn(B, T, J, 4, generator=g, dtype=F64)
    rot = rot / rot.norm(dim=-1, keepdim=True)
    root = torch.randn(B, T, 3, generator=g, dtype=F64)
    pos = skel.forward_kinematics(rot, root)
    assert pos.shape == (B, T, J, 3)
    for b in range(B):
        for t in range(T):
            torch.testing.assert_close(pos[b, t], skel.forward_kinematics(rot[b, t], root[b, t]))
    glob = skel.global_rotations(rot)
    assert glob.shape == (B, T, J, 4)
    r = rot[1, 2]
    torch.testing.assert_close(glob[1, 2, 3], quat_mul(quat_mul(r[0], r[1]), quat_mul(r[2], r[3])))


def test_fk_with_custom_per_sample_offsets():
    skel = chain()
    rot = chain_pose().expand(2, 4, 5, 4)  # (B, T, J, 4)
    root = ROOT.expand(2, 4, 3)
    offsets = torch.as_tensor(CHAIN_OFFSETS).expand(2, 5, 3).clone()
    offsets[1] *= 2.0  # the second individual is twice as big
    pos = skel.forward_kinematics(rot, root, offsets[:, None])  # offsets (B, 1, J, 3)
    assert pos.shape == (2, 4, 5, 3)
    expected = torch.tensor(CHAIN_EXPECTED, dtype=F64)
    torch.testing.assert_close(pos[0, 3], expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(pos[1, 3], ROOT + 2.0 * (expected - ROOT), atol=1e-12, rtol=0)
    # shared (J, 3) offsets other than the rest offsets
    shared = skel.forward_kinematics(chain_pose(), ROOT, 2.0 * torch.as_tensor(CHAIN_OFFSETS))
    torch.testing.assert_close(shared, pos[1, 0])


def test_rest_positions_and_bone_lengths():
    skel = chain()
    expected = [[5, 6, 7], [6, 6, 7], [6, 8, 7], [6, 8, 10], [6, 6, 8]]
    np.testing.assert_allclose(skel.rest_positions(), expected)
    assert skel.rest_positions().dtype == np.float32
    np.testing.assert_allclose(skel.bone_lengths(), [0.0, 1.0, 2.0, 3.0, 1.0])
    np.testing.assert_allclose(skel.bone_lengths(2.0 * CHAIN_OFFSETS), [0.0, 2.0, 4.0, 6.0, 2.0])
    assert skel.names == ("joint0", "joint1", "joint2", "joint3", "joint4")
    # SMPL's legs are tens of centimetres long
    assert 0.3 < SMPL22.bone_lengths()[SMPL22.index("left_knee")] < 0.5


def test_to_dict_round_trips():
    d = SMAL35.to_dict()
    again = Skeleton.from_parents(d["name"], d["parents"], np.array(d["rest_offsets"]), names=d["names"])
    assert again.names == SMAL35.names and again.parents == SMAL35.parents
    np.testing.assert_array_equal(again.rest_offsets, SMAL35.rest_offsets)


# ---------------------------------------------------------------------------------------------
# validation


@pytest.mark.parametrize(
    "parents",
    [
        [-1, 2, 0],  # parent listed after its child
        [0, 0, 1],  # no root
        [-1, -1, 1],  # two roots
        [-1, 1, 1],  # a joint its own parent
    ],
)
def test_invalid_parents_raise(parents):
    with pytest.raises(ValueError, match=r"parents must list the root first") as e:
        Skeleton.from_parents("bad", parents, np.zeros((3, 3)))
    assert str(parents) in str(e.value) and "'bad'" in str(e.value)


def test_parent_count_must_match_joints():
    with pytest.raises(ValueError, match="2 parents for 3 joints"):
        Skeleton.from_parents("bad", [-1, 0], np.zeros((3, 3)), names=["a", "b", "c"])


@pytest.mark.parametrize("group", ["face_joints", "feet_left", "feet_right", "primal_joints", "end_effectors"])
def test_out_of_range_joint_groups_raise(group):
    with pytest.raises(ValueError, match=rf"{group} has joints \[3\] outside 0..2"):
        Skeleton.from_parents("bad", [-1, 0, 1], np.zeros((3, 3)), **{group: (0, 3)})
    with pytest.raises(ValueError, match=rf"{group} has joints \[-1\]"):
        Skeleton.from_parents("bad", [-1, 0, 1], np.zeros((3, 3)), **{group: (-1,)})


def test_out_of_range_chains_raise():
    with pytest.raises(ValueError, match=r"chains has joints \[5\] outside 0..2"):
        Skeleton.from_parents("bad", [-1, 0, 1], np.zeros((3, 3)), chains=((0, 1), (1, 5)))


def test_symmetry_must_be_a_permutation():
    with pytest.raises(ValueError, match="symmetry must be a permutation of 0..2"):
        Skeleton.from_parents("bad", [-1, 0, 0], np.zeros((3, 3)), symmetry=(0, 1, 1))
    with pytest.raises(ValueError, match="symmetry"):
        Skeleton.from_parents("bad", [-1, 0, 0], np.zeros((3, 3)), symmetry=(0, 2))
