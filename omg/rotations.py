"""Batched rotation utilities in torch.

Conventions, used everywhere in omg:
- quaternions are (..., 4) in (w, x, y, z) order, unit length, Hamilton product;
- matrices are (..., 3, 3) and act on column vectors (v' = R v);
- the 6D representation is the first two *columns* of the matrix, (..., 6) =
  [R[:, 0], R[:, 1]], as in HumanML3D's ``quaternion_to_cont6d`` (so that our 263-dim
  features stay file-compatible with HumanML3D's ``new_joint_vecs``);
- Euler angles are in radians with an order string such as "ZXY" meaning intrinsic
  rotations applied in that order (R = R_Z @ R_X @ R_Y), the BVH convention.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

Tensor = torch.Tensor


def quat_identity(shape: tuple[int, ...] = (), dtype=torch.float32, device=None) -> Tensor:
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_conjugate(q: Tensor) -> Tensor:
    """Inverse of a unit quaternion."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b (apply b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_apply(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4); shapes broadcast."""
    if q.dim() != v.dim():  # linalg.cross broadcasts sizes, not numbers of dimensions
        rank = max(q.dim(), v.dim())
        q, v = q[(None,) * (rank - q.dim())], v[(None,) * (rank - v.dim())]
    w, xyz = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(xyz, v)
    return v + w * t + torch.linalg.cross(xyz, t)


def quat_between(u: Tensor, v: Tensor, eps: float = 1e-8) -> Tensor:
    """Shortest-arc rotation taking direction u to direction v (HumanML3D's ``qbetween``).

    For opposite vectors the rotation is half a turn about an axis orthogonal to u.
    """
    u = F.normalize(u, dim=-1, eps=eps)
    v = F.normalize(v, dim=-1, eps=eps)
    w = 1.0 + (u * v).sum(-1, keepdim=True)
    xyz = torch.cross(u, v, dim=-1)
    opposite = w.squeeze(-1) < 1e-6
    if opposite.any():
        # any axis orthogonal to u: cross with x, or with y when u is along x
        x_axis = torch.zeros_like(u)
        x_axis[..., 0] = 1.0
        y_axis = torch.zeros_like(u)
        y_axis[..., 1] = 1.0
        along_x = u[..., 0].abs() > 0.9
        axis = torch.cross(u, torch.where(along_x[..., None], y_axis, x_axis), dim=-1)
        xyz = torch.where(opposite[..., None], F.normalize(axis, dim=-1), xyz)
        w = torch.where(opposite[..., None], torch.zeros_like(w), w)
    return quat_normalize(torch.cat((w, xyz), dim=-1))


def quat_to_matrix(q: Tensor) -> Tensor:
    w, x, y, z = quat_normalize(q).unbind(-1)
    m = torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    )  # fmt: skip
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(m: Tensor) -> Tensor:
    """Rotation matrix to unit quaternion with w >= 0 (numerically stable branch choice)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 * (w^2, x^2, y^2, z^2); pick the largest to divide by
    sq = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), dim=-1
    )
    r = sq.clamp_min(1e-12).sqrt()  # 2 * |component|
    candidates = torch.stack(
        (
            torch.stack((r[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01), dim=-1) / (2 * r[..., 0:1]),
            torch.stack((m21 - m12, r[..., 1] ** 2, m10 + m01, m02 + m20), dim=-1) / (2 * r[..., 1:2]),
            torch.stack((m02 - m20, m10 + m01, r[..., 2] ** 2, m12 + m21), dim=-1) / (2 * r[..., 2:3]),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, r[..., 3] ** 2), dim=-1) / (2 * r[..., 3:4]),
        ),
        dim=-2,
    )  # (..., 4 candidates, 4)
    best = sq.argmax(dim=-1)
    q = torch.gather(candidates, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    q = quat_normalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def matrix_to_6d(m: Tensor) -> Tensor:
    """(..., 3, 3) -> (..., 6): first two columns, column-major as in HumanML3D."""
    return torch.cat((m[..., :, 0], m[..., :, 1]), dim=-1)


def sixd_to_matrix(d6: Tensor) -> Tensor:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt on the two columns (Zhou et al. 2019)."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = F.normalize(a1, dim=-1)
    b2 = F.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


# The 6D rotation (first two matrix columns) of a rotation seen in a mirror x -> -x: M R M with
# M = diag(-1, 1, 1) has columns -M c0 and M c1, so each entry keeps or flips its sign. The map is
# linear and exact, also on features off the rotation manifold (a generated motion's).
SIXD_REFLECT_X = (1.0, -1.0, -1.0, -1.0, 1.0, 1.0)
REFLECT_X = (-1.0, 1.0, 1.0)  # a position, velocity or offset seen in the same mirror


def quat_to_6d(q: Tensor) -> Tensor:
    return matrix_to_6d(quat_to_matrix(q))


def sixd_to_quat(d6: Tensor) -> Tensor:
    return matrix_to_quat(sixd_to_matrix(d6))


def axis_angle_to_quat(aa: Tensor) -> Tensor:
    """(..., 3) rotation vectors (axis * angle) -> (..., 4)."""
    angle = aa.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(half)/angle -> 0.5 as angle -> 0
    scale = torch.where(angle > 1e-8, torch.sin(half) / angle.clamp_min(1e-12), 0.5 - angle**2 / 48)
    return torch.cat((torch.cos(half), aa * scale), dim=-1)


def quat_to_axis_angle(q: Tensor) -> Tensor:
    q = quat_normalize(q)
    q = torch.where(q[..., :1] < 0, -q, q)
    sin_half = q[..., 1:].norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(sin_half, q[..., :1])
    scale = torch.where(sin_half > 1e-8, angle / sin_half.clamp_min(1e-12), 2.0 + angle**2 / 12)
    return q[..., 1:] * scale


_AXES = {"X": 0, "Y": 1, "Z": 2}


def euler_to_quat(angles: Tensor, order: str) -> Tensor:
    """(..., 3) angles in radians, one per letter of ``order`` -> (..., 4).

    Intrinsic order as in BVH channel lists: "ZXY" gives q = qZ * qX * qY.
    """
    order = order.upper()
    if len(order) != 3 or set(order) - set(_AXES):
        raise ValueError(f"Euler order {order!r} must be three letters from X, Y, Z (e.g. 'ZXY')")
    q = None
    for i, axis in enumerate(order):
        aa = torch.zeros(angles.shape[:-1] + (3,), dtype=angles.dtype, device=angles.device)
        aa[..., _AXES[axis]] = angles[..., i]
        qi = axis_angle_to_quat(aa)
        q = qi if q is None else quat_mul(q, qi)
    return q


def matrix_to_euler(m: Tensor, order: str) -> Tensor:
    """(..., 3, 3) -> (..., 3) intrinsic angles in ``order`` (inverse of ``euler_to_quat``)."""
    order = order.upper()
    i, j, k = (_AXES[a] for a in order)
    if len({i, j, k}) != 3:
        raise ValueError(f"Euler order {order!r} must use each of X, Y, Z once")
    # sign of the permutation (i, j, k) of (0, 1, 2)
    sign = 1.0 if (j - i) % 3 == 1 else -1.0
    a_j = torch.asin((sign * m[..., i, k]).clamp(-1.0, 1.0))
    a_i = torch.atan2(-sign * m[..., j, k], m[..., k, k])
    a_k = torch.atan2(-sign * m[..., i, j], m[..., i, i])
    # gimbal lock (middle angle ±90°): only a_i ± a_k is defined; put it all in a_i
    locked = m[..., i, k].abs() > 1.0 - 1e-6
    a_i = torch.where(locked, torch.atan2(sign * m[..., k, j], m[..., j, j]), a_i)
    a_k = torch.where(locked, torch.zeros_like(a_k), a_k)
    return torch.stack((a_i, a_j, a_k), dim=-1)


def quat_to_euler(q: Tensor, order: str) -> Tensor:
    return matrix_to_euler(quat_to_matrix(q), order)


def quat_slerp(a: Tensor, b: Tensor, t: Tensor | float) -> Tensor:
    """Spherical interpolation from a (t=0) to b (t=1) along the shorter arc."""
    t = torch.as_tensor(t, dtype=a.dtype, device=a.device)
    dot = (a * b).sum(-1, keepdim=True)
    b = torch.where(dot < 0, -b, b)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    sin_theta = torch.sin(theta)
    small = sin_theta < 1e-6
    wa = torch.where(small, 1 - t, torch.sin((1 - t) * theta) / sin_theta.clamp_min(1e-12))
    wb = torch.where(small, t, torch.sin(t * theta) / sin_theta.clamp_min(1e-12))
    return quat_normalize(wa * a + wb * b)


def yaw_quat(angle: Tensor) -> Tensor:
    """Rotation by ``angle`` radians about +Y (the up axis), (...,) -> (..., 4)."""
    zeros = torch.zeros_like(angle)
    return torch.stack((torch.cos(angle / 2), zeros, torch.sin(angle / 2), zeros), dim=-1)
