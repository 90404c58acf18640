"""Kinematics shared by importers, retargeting, representations, training and export.

One home for three algorithms that several layers need:

- ``kabsch``: the rotation that best turns a set of rest vectors onto observed ones (and
  ``nearest_rotation``, its case of the three axes: the rotation nearest a matrix);
- ``positions_to_rotations`` (with ``clip_offsets``): local joint rotations that reproduce
  joint positions by forward kinematics (inverse kinematics on a fixed skeleton);
- ``foot_contacts``: HumanML3D's contact rule, a foot joint slower than a speed between two
  frames (``FOOT_THRESHOLD``, 0.002 m² per 20-fps frame); ``ground_contacts`` adds
  retargeting's "and low" condition (within ``GROUND_CONTACT_BAND`` of the clip's floor).

Foundation layer: imports only omg.rotations and omg.skeleton (plus numpy and torch).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from omg.rotations import matrix_to_quat, quat_apply, quat_between, quat_conjugate, quat_identity, quat_mul
from omg.skeleton import Skeleton

Tensor = torch.Tensor

# HumanML3D's foot-contact threshold is a squared displacement per 20-fps frame; as a speed it
# means the same at any fps (and gives HumanML3D's own contacts at 20 fps)
FOOT_THRESHOLD = 0.002  # m^2 per frame at FOOT_THRESHOLD_FPS: under it a foot is in contact
FOOT_THRESHOLD_FPS = 20.0
FOOT_CONTACT_SPEED = math.sqrt(FOOT_THRESHOLD) * FOOT_THRESHOLD_FPS  # ≈ 0.894 m/s
# retargeting's ground contact: slower than this and low
GROUND_CONTACT_SPEED = 0.3  # m/s
GROUND_CONTACT_BAND = 0.10  # m: "low" = within this of the clip's lowest foot joints


def kabsch(rest: Tensor, observed: Tensor, weights: Tensor | None = None) -> Tensor:
    """(..., C, 3) rest vectors, (..., C, 3) observed ones (broadcast against each other),
    optional (..., C) weights -> (..., 3, 3) rotation R minimising sum_c w_c |R rest_c - observed_c|².

    The vectors are not centred (they are bones from one joint, or directions). Where the best
    orthogonal fit is a reflection (coplanar or too few vectors), the axis of the smallest
    singular value is flipped, so that R is always a proper rotation (det +1).
    """
    if weights is not None:
        rest = rest * weights[..., None]
    U, _, Vh = torch.linalg.svd(rest.transpose(-1, -2) @ observed)  # of the (..., 3, 3) cross-covariance
    V, Ut = Vh.transpose(-1, -2), U.transpose(-1, -2)
    d = torch.sign(torch.linalg.det(V @ Ut))
    d = torch.where(d == 0, torch.ones_like(d), d)
    return V @ torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1)) @ Ut


def nearest_rotation(m: Tensor) -> Tensor:
    """(..., 3, 3) -> the rotation R nearest m in the Frobenius norm (the polar factor, det +1): Kabsch of the
    identity's axes onto m's columns. The mean of rotation matrices is no rotation; this is the mean rotation."""
    eye = torch.eye(3, dtype=m.dtype, device=m.device).expand_as(m)
    return kabsch(eye, m.transpose(-1, -2))


def clip_offsets(skeleton: Skeleton, positions: Tensor) -> Tensor:
    """(T, J, 3) -> (J, 3) rest offsets for IK: the skeleton's bone directions, the clip's mean lengths.

    The child bones of a joint with several (hips and spine from the pelvis) keep the angles
    between them that the clip has, turned to fit the skeleton's directions best: no rotation
    can match them otherwise (HumanML3D's uniform skeleton has its hips level, SMPL's drop).
    """
    rest = torch.as_tensor(skeleton.rest_offsets, dtype=positions.dtype)
    dirs = F.normalize(rest, dim=-1)
    for j in range(skeleton.num_joints):
        children = skeleton.children(j)
        if len(children) > 1:
            observed = F.normalize(positions[:, children] - positions[:, j, None], dim=-1)  # (T, C, 3)
            R = kabsch(dirs[children], observed)  # (T, 3, 3)
            dirs[children] = F.normalize((observed @ R).mean(0), dim=-1)  # R^T o per frame, averaged
    parents = torch.tensor(skeleton.parents[1:])
    lengths = (positions[:, 1:] - positions[:, parents]).norm(dim=-1).mean(0)  # (J - 1,)
    return torch.cat([rest[:1], dirs[1:] * lengths[:, None]])


def positions_to_rotations(
    skeleton: Skeleton,
    positions: Tensor,  # (..., J, 3), e.g. (T, J, 3)
    offsets: Tensor,  # (J, 3) rest offsets of the skeleton the rotations drive
    placed: Sequence[bool] | None = None,
    aim_from_fk: bool = True,
) -> Tensor:  # (..., J, 4) local rotations
    """Local joint rotations that reproduce ``positions`` by forward kinematics from ``positions[..., 0, :]``.

    Parents first, each joint turns the rest directions of its child bones (``offsets``) onto
    the observed ones: a joint with one child bone gets the shortest arc in its parent's frame
    (no twist of its own: smooth in time, as a tracked limb would be); one with several (pelvis,
    chest) gets their best fit (``kabsch``). Leaf joints, whose twist no position shows, keep
    the identity, as do joints whose child bones are all of zero length or not ``placed``.

    ``placed``: (J,) which joints' positions are known (default: all); a joint outside it has
    no bone to aim at and follows its parent rigidly. ``aim_from_fk``: aim each joint's bones
    from where forward kinematics has put the joint so far (errors do not accumulate along a
    chain: exact where the offsets fit), else from its observed position (each bone copies its
    observed direction; retargeting's choice, whose sources are rigs of their own).
    """
    J = skeleton.num_joints
    if positions.shape[-2:] != (J, 3) or offsets.shape != (J, 3):
        raise ValueError(f"positions must be (..., {J}, 3) and offsets ({J}, 3) for {skeleton.name!r}, "
                         f"got {tuple(positions.shape)} and {tuple(offsets.shape)}")  # fmt: skip
    placed = [True] * J if placed is None else [bool(p) for p in placed]
    offsets = offsets.to(positions.dtype)
    has_length = (offsets.norm(dim=-1) > 1e-9).tolist()
    frames = positions.shape[:-2]
    local = quat_identity((*frames, J), dtype=positions.dtype, device=positions.device)
    identity = quat_identity(frames, dtype=positions.dtype, device=positions.device)
    world = [identity] * J  # (..., 4) global rotations
    fk = [positions[..., 0, :]] * J  # (..., 3) joint positions as FK places them
    for j, p in enumerate(skeleton.parents):
        parent_rot = world[p] if p >= 0 else identity
        if p >= 0:
            fk[j] = fk[p] + quat_apply(parent_rot, offsets[j])
        origin = fk[j] if aim_from_fk else positions[..., j, :]
        kids = [c for c in skeleton.children(j) if placed[j] and placed[c] and has_length[c]]
        if len(kids) == 1:
            aim = quat_apply(quat_conjugate(parent_rot), positions[..., kids[0], :] - origin)  # in the parent frame
            local[..., j, :] = quat_between(offsets[kids[0]].expand_as(aim), aim)
        elif kids:
            aim = F.normalize(positions[..., kids, :] - origin[..., None, :], dim=-1)  # (..., C, 3)
            best = matrix_to_quat(kabsch(F.normalize(offsets[kids], dim=-1), aim))
            local[..., j, :] = quat_mul(quat_conjugate(parent_rot), best)
        world[j] = quat_mul(parent_rot, local[..., j, :])
    return local


def foot_contacts(
    positions: Tensor, feet: Sequence[int], fps: float, *, max_speed: float = FOOT_CONTACT_SPEED
) -> Tensor:
    """(..., T, J, 3) positions -> (..., T-1, F) bool: each of the ``feet`` joints moves slower than
    ``max_speed`` between frames t and t+1 (default HumanML3D's contact speed, ``FOOT_CONTACT_SPEED``:
    0.002 m² per 20-fps frame, the same speed at any fps)."""
    feet = list(feet)
    step = positions[..., 1:, feet, :] - positions[..., :-1, feet, :]  # (..., T-1, F, 3)
    return step.square().sum(-1) < (max_speed / fps) ** 2


def ground_contacts(
    positions: Tensor,
    feet: Sequence[int],
    fps: float,
    *,
    max_speed: float = GROUND_CONTACT_SPEED,
    band: float = GROUND_CONTACT_BAND,
) -> Tensor:
    """(T, J, 3) Y-up positions -> (T, F) bool: each of the ``feet`` joints slower than ``max_speed``
    (``foot_contacts``; the last frame repeats the one before) and within ``band`` of the clip's
    lowest foot heights (their 2nd percentile over the clip: robust to a stray frame)."""
    height = positions[:, list(feet), 1]  # (T, F)
    base = float(torch.quantile(height.min(1).values, 0.02))
    slow = foot_contacts(positions, feet, fps, max_speed=max_speed)  # (T-1, F)
    return torch.cat([slow, slow[-1:]]) & (height < base + band)
