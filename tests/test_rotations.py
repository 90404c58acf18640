"""Rotation utilities checked against each other, against hand-written matrices and against scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from omg import rotations as R

Rotation = pytest.importorskip("scipy.spatial.transform").Rotation

N = 1000
ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]
F64 = torch.float64


# ---------------------------------------------------------------------------------------------
# helpers


def random_quats(n: int = N, seed: int = 0) -> torch.Tensor:
    """(n, 4) uniformly random unit quaternions (float64)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=F64)
    return q / q.norm(dim=-1, keepdim=True)


def random_vectors(n: int = N, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(n, 3, generator=g, dtype=F64)


def scipy_matrix(q: torch.Tensor) -> torch.Tensor:
    """Independent reference: scipy's matrix for (w, x, y, z) quaternions."""
    xyzw = q[..., [1, 2, 3, 0]].reshape(-1, 4).numpy()
    return torch.from_numpy(Rotation.from_quat(xyzw).as_matrix()).reshape(q.shape[:-1] + (3, 3))


def same_rotation(q1: torch.Tensor, q2: torch.Tensor, atol: float = 1e-9) -> None:
    """q and -q are the same rotation."""
    err = torch.minimum((q1 - q2).abs().amax(-1), (q1 + q2).abs().amax(-1))
    assert err.max().item() < atol, err.max().item()


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


AXIS_MATRIX = {"X": rot_x, "Y": rot_y, "Z": rot_z}


def hand_euler_matrix(angles, order: str) -> np.ndarray:
    """Intrinsic Euler by hand: "ZXY" with (a, b, c) is R_Z(a) @ R_X(b) @ R_Y(c)."""
    m = np.eye(3)
    for axis, angle in zip(order, angles):
        m = m @ AXIS_MATRIX[axis](angle)
    return m


def quat(*wxyz) -> torch.Tensor:
    return torch.tensor(wxyz, dtype=F64)


# ---------------------------------------------------------------------------------------------
# quaternion <-> matrix


def test_quat_to_matrix_matches_scipy_and_is_a_rotation():
    q = random_quats()
    m = R.quat_to_matrix(q)
    torch.testing.assert_close(m, scipy_matrix(q), atol=1e-12, rtol=0)
    eye = torch.eye(3, dtype=F64).expand(N, 3, 3)
    torch.testing.assert_close(m @ m.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(m), torch.ones(N, dtype=F64), atol=1e-12, rtol=0)


def test_quat_matrix_quat_round_trip_up_to_sign():
    q = random_quats()
    back = R.matrix_to_quat(R.quat_to_matrix(q))
    same_rotation(back, q)
    assert (back[:, 0] >= 0).all(), "matrix_to_quat returns w >= 0"


def test_matrix_to_quat_half_turns():
    """w = 0 is where naive formulas divide by zero."""
    axes = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, -1, 1], [1, 1, 1]], dtype=F64)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    q = torch.cat((torch.zeros(len(axes), 1, dtype=F64), axes), dim=-1)
    m = scipy_matrix(q)
    back = R.matrix_to_quat(m)
    same_rotation(back, q)
    torch.testing.assert_close(R.quat_to_matrix(back), m, atol=1e-12, rtol=0)


def test_matrix_to_quat_float32_is_accurate():
    q = random_quats().float()
    same_rotation(R.matrix_to_quat(R.quat_to_matrix(q)), q, atol=1e-5)


def test_quat_to_matrix_known_quarter_turn():
    q = quat(math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4))  # 90 deg about +Z
    expected = torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=F64)
    torch.testing.assert_close(R.quat_to_matrix(q), expected, atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------------
# products, application, inverse


def test_quat_mul_is_matrix_product():
    a, b = random_quats(seed=2), random_quats(seed=3)
    ab = R.quat_mul(a, b)
    torch.testing.assert_close(R.quat_to_matrix(ab), R.quat_to_matrix(a) @ R.quat_to_matrix(b), atol=1e-12, rtol=0)
    torch.testing.assert_close(ab.norm(dim=-1), torch.ones(N, dtype=F64), atol=1e-12, rtol=0)


def test_quat_apply_is_matrix_times_vector():
    q, v = random_quats(), random_vectors()
    expected = (R.quat_to_matrix(q) @ v[..., None])[..., 0]
    torch.testing.assert_close(R.quat_apply(q, v), expected, atol=1e-12, rtol=0)
    ref = torch.from_numpy(Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).apply(v.numpy()))
    torch.testing.assert_close(R.quat_apply(q, v), ref, atol=1e-12, rtol=0)


def test_quat_apply_broadcasts():
    q = random_quats(5)[:, None]  # (5, 1, 4)
    v = random_vectors(7)  # (7, 3)
    out = R.quat_apply(q, v)
    assert out.shape == (5, 7, 3)
    torch.testing.assert_close(out[3, 4], R.quat_apply(q[3, 0], v[4]))
    one = R.quat_apply(q[2, 0], v)  # one rotation (4,) for every vector (7, 3)
    assert one.shape == (7, 3) and torch.equal(one, out[2])


def test_quat_conjugate_is_inverse():
    q, v = random_quats(), random_vectors()
    identity = R.quat_identity((N,), dtype=F64)
    same_rotation(R.quat_mul(q, R.quat_conjugate(q)), identity, atol=1e-12)
    same_rotation(R.quat_mul(R.quat_conjugate(q), q), identity, atol=1e-12)
    torch.testing.assert_close(R.quat_apply(R.quat_conjugate(q), R.quat_apply(q, v)), v, atol=1e-12, rtol=0)
    torch.testing.assert_close(R.quat_to_matrix(R.quat_conjugate(q)), R.quat_to_matrix(q).transpose(-1, -2))


def test_quat_identity():
    q = R.quat_identity((2, 3))
    assert q.shape == (2, 3, 4) and q.dtype == torch.float32
    assert torch.equal(q[1, 2], torch.tensor([1.0, 0.0, 0.0, 0.0]))


# ---------------------------------------------------------------------------------------------
# 6D


def test_6d_is_first_two_columns():
    m = R.quat_to_matrix(random_quats())
    d6 = R.matrix_to_6d(m)
    assert d6.shape == (N, 6)
    torch.testing.assert_close(d6[:, :3], m[:, :, 0], atol=0, rtol=0)
    torch.testing.assert_close(d6[:, 3:], m[:, :, 1], atol=0, rtol=0)


def test_6d_round_trips():
    q = random_quats()
    m = R.quat_to_matrix(q)
    torch.testing.assert_close(R.sixd_to_matrix(R.matrix_to_6d(m)), m, atol=1e-12, rtol=0)
    torch.testing.assert_close(R.quat_to_6d(q), R.matrix_to_6d(m))
    same_rotation(R.sixd_to_quat(R.quat_to_6d(q)), q)


def test_sixd_to_matrix_orthonormalises_noisy_input():
    g = torch.Generator().manual_seed(4)
    d6 = torch.randn(N, 6, generator=g, dtype=F64)  # not orthogonal, not unit length
    m = R.sixd_to_matrix(d6)
    eye = torch.eye(3, dtype=F64).expand(N, 3, 3)
    torch.testing.assert_close(m.transpose(-1, -2) @ m, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(m), torch.ones(N, dtype=F64), atol=1e-12, rtol=0)
    # Gram-Schmidt: the first column is the first vector's direction, the second stays in its plane
    a1, a2 = d6[:, :3], d6[:, 3:]
    torch.testing.assert_close(m[:, :, 0], a1 / a1.norm(dim=-1, keepdim=True))
    assert (torch.einsum("ni,ni->n", m[:, :, 1], a2) > 0).all()
    torch.testing.assert_close(torch.einsum("ni,ni->n", m[:, :, 2], a2), torch.zeros(N, dtype=F64), atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------------
# axis-angle


def test_axis_angle_round_trip_matches_scipy():
    q = random_quats()
    q = torch.where(q[:, :1] < 0, -q, q)
    aa = R.quat_to_axis_angle(q)
    ref = torch.from_numpy(Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_rotvec())
    torch.testing.assert_close(aa, ref, atol=1e-10, rtol=0)
    assert (aa.norm(dim=-1) <= math.pi + 1e-12).all()
    same_rotation(R.axis_angle_to_quat(aa), q)


def test_axis_angle_known_values():
    aa = torch.tensor([0.0, 0.0, math.pi / 2], dtype=F64)
    torch.testing.assert_close(R.axis_angle_to_quat(aa), quat(math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)))
    torch.testing.assert_close(R.axis_angle_to_quat(torch.zeros(3, dtype=F64)), quat(1, 0, 0, 0))
    torch.testing.assert_close(R.quat_to_axis_angle(quat(1, 0, 0, 0)), torch.zeros(3, dtype=F64))


@pytest.mark.parametrize("angle", [1e-12, 1e-9, 1e-7, 1e-4])
def test_axis_angle_tiny_angles(angle):
    axis = torch.tensor([0.6, -0.0, 0.8], dtype=F64)
    aa = axis * angle
    q = R.axis_angle_to_quat(aa)
    assert torch.isfinite(q).all()
    expected = torch.cat((torch.tensor([math.cos(angle / 2)], dtype=F64), aa / 2))
    torch.testing.assert_close(q, expected, atol=1e-15, rtol=1e-9)
    back = R.quat_to_axis_angle(q)
    torch.testing.assert_close(back, aa, atol=1e-18, rtol=1e-9)


@pytest.mark.parametrize("delta", [1e-3, 1e-6, 0.0])
def test_axis_angle_near_half_turn(delta):
    axis = torch.tensor([2.0, -1.0, 2.0], dtype=F64) / 3.0
    aa = axis * (math.pi - delta)
    q = R.axis_angle_to_quat(aa)
    torch.testing.assert_close(R.quat_to_matrix(q), torch.from_numpy(Rotation.from_rotvec(aa.numpy()).as_matrix()))
    back = R.quat_to_axis_angle(q)
    assert back.norm().item() == pytest.approx(math.pi - delta, abs=1e-9)
    if delta > 0:  # below pi the rotation vector is unique
        torch.testing.assert_close(back, aa, atol=1e-9, rtol=0)
    else:  # at pi, +axis and -axis are the same rotation
        assert min((back - aa).abs().max(), (back + aa).abs().max()) < 1e-9


def test_axis_angle_float32_near_zero_and_pi():
    aa = torch.tensor([[1e-6, 0.0, 0.0], [0.0, 0.0, math.pi - 1e-4]], dtype=torch.float32)
    back = R.quat_to_axis_angle(R.axis_angle_to_quat(aa))
    torch.testing.assert_close(back, aa, atol=1e-5, rtol=1e-3)


# ---------------------------------------------------------------------------------------------
# Euler angles


def random_euler(n: int = N, seed: int = 5) -> torch.Tensor:
    """Angles away from gimbal lock: outer in (-pi, pi), middle in (-pi/2, pi/2) by a margin."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1
    return u * torch.tensor([math.pi - 0.01, math.pi / 2 - 0.05, math.pi - 0.01], dtype=F64)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_matches_scipy_intrinsic(order):
    angles = random_euler()
    m = R.quat_to_matrix(R.euler_to_quat(angles, order))
    ref = torch.from_numpy(Rotation.from_euler(order, angles.numpy()).as_matrix())  # upper case = intrinsic
    torch.testing.assert_close(m, ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_quat_euler_round_trip(order):
    angles = random_euler()
    q = R.euler_to_quat(angles, order)
    torch.testing.assert_close(R.quat_to_euler(q, order), angles, atol=1e-9, rtol=0)
    torch.testing.assert_close(R.matrix_to_euler(R.quat_to_matrix(q), order), angles, atol=1e-9, rtol=0)


@pytest.mark.parametrize("order", ORDERS)
def test_quat_euler_quat_round_trip(order):
    q = random_quats(seed=6)
    same_rotation(R.euler_to_quat(R.quat_to_euler(q, order), order), q, atol=1e-7)


@pytest.mark.parametrize("order", ORDERS)
def test_euler_hand_computed(order):
    """Each order against hand-written axis matrices, and one literal quarter-turn case."""
    for angles in [(0.3, -0.7, 1.1), (-2.0, 0.4, 2.5)]:
        m = R.quat_to_matrix(R.euler_to_quat(torch.tensor(angles, dtype=F64), order))
        torch.testing.assert_close(m, torch.from_numpy(hand_euler_matrix(angles, order)), atol=1e-12, rtol=0)
    # 90 deg about the first axis then 90 deg about the second (intrinsic): a signed permutation
    quarter = torch.tensor([math.pi / 2, math.pi / 2, 0.0], dtype=F64)
    m = R.quat_to_matrix(R.euler_to_quat(quarter, order))
    torch.testing.assert_close(m, torch.tensor(QUARTER_TURNS[order], dtype=F64), atol=1e-12, rtol=0)


# R_first(90) @ R_second(90), written out by hand from the axis matrices
QUARTER_TURNS = {
    "XYZ": [[0, 0, 1], [1, 0, 0], [0, 1, 0]],  # Rx90 @ Ry90
    "XZY": [[0, -1, 0], [0, 0, -1], [1, 0, 0]],  # Rx90 @ Rz90
    "YXZ": [[0, 1, 0], [0, 0, -1], [-1, 0, 0]],  # Ry90 @ Rx90
    "YZX": [[0, 0, 1], [1, 0, 0], [0, 1, 0]],  # Ry90 @ Rz90
    "ZXY": [[0, 0, 1], [1, 0, 0], [0, 1, 0]],  # Rz90 @ Rx90
    "ZYX": [[0, -1, 0], [0, 0, 1], [-1, 0, 0]],  # Rz90 @ Ry90
}


def test_single_axis_quarter_turns_every_order():
    """A 90 deg angle in slot i of any order is a quarter turn about that letter's axis."""
    known = {
        "X": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        "Y": [[0, 0, 1], [0, 1, 0], [-1, 0, 0]],
        "Z": [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
    }
    for order in ORDERS:
        for slot, axis in enumerate(order):
            angles = torch.zeros(3, dtype=F64)
            angles[slot] = math.pi / 2
            m = R.quat_to_matrix(R.euler_to_quat(angles, order))
            torch.testing.assert_close(m, torch.tensor(known[axis], dtype=F64), atol=1e-12, rtol=0)


def test_euler_accepts_lower_case_and_rejects_bad_orders():
    angles = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    torch.testing.assert_close(R.euler_to_quat(angles, "zxy"), R.euler_to_quat(angles, "ZXY"))
    torch.testing.assert_close(R.matrix_to_euler(R.quat_to_matrix(R.euler_to_quat(angles, "ZXY")), "zxy"), angles)
    for bad in ["XY", "XYW", "XYZX"]:
        with pytest.raises(ValueError, match=bad):
            R.euler_to_quat(angles, bad)
    with pytest.raises(ValueError, match="XXY"):
        R.matrix_to_euler(torch.eye(3, dtype=F64), "XXY")


# ---------------------------------------------------------------------------------------------
# quat_between, slerp, yaw


def test_quat_between_maps_u_to_v():
    u, v = random_vectors(seed=7), random_vectors(seed=8) * 3.0
    q = R.quat_between(u, v)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(N, dtype=F64), atol=1e-12, rtol=0)
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    torch.testing.assert_close(R.quat_apply(q, unit(u)), unit(v), atol=1e-10, rtol=0)
    # shortest arc: the rotation angle is the angle between u and v, about an axis normal to both
    angle = 2 * torch.atan2(q[:, 1:].norm(dim=-1), q[:, 0])
    torch.testing.assert_close(angle, torch.arccos((unit(u) * unit(v)).sum(-1).clamp(-1, 1)), atol=1e-7, rtol=0)
    torch.testing.assert_close((q[:, 1:] * u).sum(-1), torch.zeros(N, dtype=F64), atol=1e-10, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_quat_between_opposite_and_equal_vectors(dtype):
    u = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 2, 3], [-0.3, 0.1, 0.9], [1, 0, 0]], dtype=dtype)
    v = -u
    v[-1] = u[-1]  # equal vectors: identity
    q = R.quat_between(u, v)
    assert torch.isfinite(q).all()
    unit = u / u.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(R.quat_apply(q, unit), v / v.norm(dim=-1, keepdim=True), atol=1e-5, rtol=0)
    torch.testing.assert_close(q[:-1, 0], torch.zeros(5, dtype=dtype), atol=1e-6, rtol=0)  # half turns
    torch.testing.assert_close(q[-1], torch.tensor([1.0, 0, 0, 0], dtype=dtype))


def test_slerp_endpoints_and_midpoint():
    a, b = random_quats(seed=9), random_quats(seed=10)
    same_rotation(R.quat_slerp(a, b, 0.0), a, atol=1e-12)
    same_rotation(R.quat_slerp(a, b, 1.0), b, atol=1e-12)
    mid = R.quat_slerp(a, b, 0.5)
    # the midpoint is equally far from both ends, half the (shorter-arc) angle each
    rel = lambda x, y: 2 * torch.acos(R.quat_mul(R.quat_conjugate(x), y)[:, 0].abs().clamp(max=1))  # noqa: E731
    torch.testing.assert_close(rel(a, mid), rel(a, b) / 2, atol=1e-7, rtol=0)
    torch.testing.assert_close(rel(mid, b), rel(a, b) / 2, atol=1e-7, rtol=0)


def test_slerp_about_one_axis_and_shorter_arc():
    a = R.quat_identity((), dtype=F64)
    b = R.axis_angle_to_quat(torch.tensor([0.0, 1.2, 0.0], dtype=F64))
    t = torch.tensor([[0.0], [0.25], [0.5], [1.0]], dtype=F64)
    expected = R.axis_angle_to_quat(torch.tensor([0.0, 1.2, 0.0], dtype=F64) * t)
    torch.testing.assert_close(R.quat_slerp(a, b, t), expected)
    same_rotation(R.quat_slerp(a, -b, t), expected)  # -b is the same rotation: same path
    # nearly equal quaternions do not divide by zero
    c = R.axis_angle_to_quat(torch.tensor([1e-9, 0.0, 0.0], dtype=F64))
    assert torch.isfinite(R.quat_slerp(a, c, 0.5)).all()


def test_yaw_quat_turns_forward_towards_left():
    """+90 deg yaw about +Y takes +Z (forward) to +X (left)."""
    q = R.yaw_quat(torch.tensor([math.pi / 2, 0.0, -math.pi / 2], dtype=F64))
    assert q.shape == (3, 4)
    forward = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    torch.testing.assert_close(
        R.quat_apply(q, forward), torch.tensor([[1.0, 0, 0], [0, 0, 1], [-1, 0, 0]], dtype=F64), atol=1e-12, rtol=0
    )
    angles = torch.linspace(-3, 3, 13, dtype=F64)
    expected = torch.stack([torch.from_numpy(rot_y(a)) for a in angles.tolist()])
    torch.testing.assert_close(R.quat_to_matrix(R.yaw_quat(angles)), expected)


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
@pytest.mark.parametrize("middle", [math.pi / 2, -math.pi / 2])
def test_euler_at_gimbal_lock_reproduces_the_rotation(order, middle):
    m = R.quat_to_matrix(R.euler_to_quat(torch.tensor([0.5, middle, 0.3], dtype=torch.float64), order))
    back = R.quat_to_matrix(R.euler_to_quat(R.matrix_to_euler(m, order), order))
    torch.testing.assert_close(back, m, rtol=0, atol=1e-6)
