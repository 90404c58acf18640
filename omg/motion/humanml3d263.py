"""HumanML3D's 263-dim motion features on SMPL-22, a faithful port of its processing.

Port of EricGuo5513/HumanML3D (motion_representation.ipynb ``process_file``,
``recover_from_ric`` / ``recover_from_rot``, common/skeleton.py ``inverse_kinematics_np``,
cal_mean_variance.ipynb), kept file-compatible with its ``new_joint_vecs``:

1. uniform skeleton: every bone keeps its direction and gets the target length (the
   skeleton's rest bone lengths); the root trajectory is scaled by the ratio of leg lengths;
2. put on the floor, root XZ of frame 0 at the origin, frame 0 turned to face +Z;
3. IK to per-bone quaternions, with the heading smoothed over time (gaussian, sigma 20 frames),
   except frame 0, whose root rotation IK sets to the identity;
4. per frame t (velocities t -> t+1, so T - 1 rows):
   [0] root yaw velocity, [1:3] root XZ velocity, [3] root height, [4:67] joints 1..21
   relative to the root in its heading frame (ric), [67:193] IK rotations of joints 1..21
   in 6D, [193:259] joint velocities in the heading frame, [259:263] foot contacts
   (left 7, 10; right 8, 11).

Two HumanML3D details are kept on purpose because its files contain them:
- its IK unpacks the face joints (r_hip, l_hip, r_shoulder, l_shoulder) as
  (l_hip, r_hip, ...), so the hip term of the heading has the opposite sign to the one of
  step 2; together with the smoothing, the IK heading is a few degrees off the facing;
- its IK (``inverse_kinematics_np``) sets the root rotation of frame 0 to the identity
  (``root_quat[0] = [1, 0, 0, 0]``) instead of the smoothed heading, and every frame-0
  feature follows from it: [0] is the yaw from the identity to frame 1's heading, and the
  ric, the 6D rotations (relative to that identity root) and the local velocities of frame 0
  are taken in the frame of step 2 (facing +Z by the unsmoothed face joints).
  ``recover_from_ric`` starts the heading at zero, i.e. at that same identity, so decoded
  positions are exactly the ones of step 2, which ``canonicalize`` returns (HumanML3D's
  ``new_joints``): ``decode(encode(x)) == canonicalize(x)[:-1]``, and FK of the rotations
  (``recover_from_rot``) gives the same positions.

Quaternions here follow HumanML3D's skeleton: the rotation stored at joint j turns the
bone parent(j) -> j from its rest direction (``T2M_RAW_OFFSETS``), relative to the previous
bone of its kinematic chain (the root for the first bone of each chain).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from omg.errors import UsageError
from omg.kinematics import foot_contacts
from omg.motion.base import Clip, Representation, check_mirrorable, mirror_block
from omg.registry import REPRESENTATIONS
from omg.rotations import (
    REFLECT_X,
    SIXD_REFLECT_X,
    quat_apply,
    quat_between,
    quat_conjugate,
    quat_mul,
    quat_to_6d,
    quat_to_matrix,
    sixd_to_matrix,
)
from omg.skeleton import SMPL22_PARENTS, Skeleton

# HumanML3D paramUtil: each bone's direction in the rest pose, and the kinematic chains
T2M_RAW_OFFSETS = np.array(
    [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
     [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
     [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]],
    dtype=np.float64,
)  # fmt: skip
T2M_CHAINS = ((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20))
FACE_JOINTS = (2, 1, 17, 16)  # right hip, left hip, right shoulder, left shoulder
FEET_LEFT, FEET_RIGHT = (7, 10), (8, 11)
LEG_JOINTS = (5, 8)  # right knee, right ankle: their bones set the scale of the root trajectory
# HumanML3D's constants are per 20-fps frame; as a speed and a time they mean the same at any fps
# (and give HumanML3D's own values at 20 fps). Its foot-contact rule (FOOT_THRESHOLD, 0.002 m² per
# 20-fps frame, i.e. FOOT_CONTACT_SPEED) is omg.kinematics.foot_contacts.
HUMANML3D_FPS = 20.0
HEADING_SIGMA = 20.0  # frames at 20 fps: the heading is smoothed over about a second
# feature groups whose std is averaged (cal_mean_variance); the root and contact groups
# are the ones T2M's loaders divide by feat_bias
GROUPS = ((0, 1), (1, 3), (3, 4), (4, 67), (67, 193), (193, 259), (259, 263))
BIASED_GROUPS = ((0, 1), (1, 3), (3, 4), (259, 263))

_UP = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
_FORWARD = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
_XZ = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)


def gaussian_filter1d(x: np.ndarray, sigma: float) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter1d(x, sigma, axis=0, mode="nearest")`` in numpy."""
    radius = int(4.0 * sigma + 0.5)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    padded = np.pad(x, [(radius, radius)] + [(0, 0)] * (x.ndim - 1), mode="edge")
    return sum(w * padded[i : i + len(x)] for i, w in enumerate(kernel / kernel.sum()))


def _heading(across: torch.Tensor) -> torch.Tensor:
    """(..., 3) vector from the left to the right side -> (..., 4) yaw turning the facing to +Z."""
    forward = F.normalize(torch.cross(_UP.expand_as(across), across, dim=-1), dim=-1)
    return quat_between(forward, _FORWARD.expand_as(forward))


def inverse_kinematics(joints: torch.Tensor, fps: float = HUMANML3D_FPS) -> torch.Tensor:
    """(T, 22, 3) -> (T, 22, 4): HumanML3D's ``inverse_kinematics_np(smooth_forward=True)``, its
    heading smoothing scaled to ``fps``.

    As there, the root rotation of frame 0 is the identity, not the smoothed heading, and the
    rotations of frame 0's chains are relative to it.
    """
    r_hip, l_hip, r_shoulder, l_shoulder = FACE_JOINTS
    # their hip term is left - right (see the module docstring), the shoulder term right - left
    across = (joints[:, l_hip] - joints[:, r_hip]) + (joints[:, r_shoulder] - joints[:, l_shoulder])
    forward = torch.cross(_UP.expand_as(across), F.normalize(across, dim=-1), dim=-1)
    sigma = HEADING_SIGMA * fps / HUMANML3D_FPS
    forward = F.normalize(torch.from_numpy(gaussian_filter1d(forward.numpy(), sigma)), dim=-1)
    root = quat_between(forward, _FORWARD.expand_as(forward))  # (T, 4)
    root[0] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=root.dtype)  # HumanML3D: root_quat[0] = identity
    quats = [root] * 22
    raw = torch.from_numpy(T2M_RAW_OFFSETS)
    for chain in T2M_CHAINS:
        R = root
        for a, b in zip(chain[:-1], chain[1:]):
            bone = quat_between(raw[b].expand_as(joints[:, b]), joints[:, b] - joints[:, a])
            quats[b] = quat_mul(quat_conjugate(R), bone)
            R = quat_mul(R, quats[b])
    return torch.stack(quats, dim=1)


@REPRESENTATIONS.register("humanml3d263")
class HumanML3D263(Representation):
    """HumanML3D's 263 features per frame on SMPL-22 (T' = T - 1); see the module docstring.

    ``feat_bias`` divides the std of the root and foot-contact groups in ``finalize_stats``
    (T2M's training loaders use 5); 1.0 reproduces HumanML3D's ``Std.npy``.
    """

    name = "humanml3d263"
    frames_dropped = 1
    stance_root = True  # foot contacts and a root velocity: root_from_stance

    def __init__(self, skeleton: Skeleton | str = "smpl22", feat_bias: float = 1.0):
        super().__init__(skeleton)
        if list(self.skeleton.parents) != SMPL22_PARENTS:
            raise UsageError(
                f"representation 'humanml3d263' needs the SMPL-22 hierarchy (skeleton smpl22), "
                f"got skeleton {self.skeleton.name!r} with {self.skeleton.num_joints} joints"
            )
        self.feat_bias = feat_bias
        lengths = self.skeleton.bone_lengths().astype(np.float64)  # (22,)
        self.target_offsets = T2M_RAW_OFFSETS * lengths[:, None]  # (22, 3) the uniform skeleton

    @property
    def dim(self) -> int:
        return 263

    def _global_positions(self, positions: np.ndarray) -> torch.Tensor:
        """(T, 22, 3) -> uniform skeleton, on the floor, root XZ at the origin, frame 0 facing +Z."""
        p = torch.as_tensor(np.asarray(positions, dtype=np.float64))
        if p.ndim != 3 or p.shape[1:] != (22, 3) or len(p) < 2 or not torch.isfinite(p).all():
            raise UsageError(f"humanml3d263 needs finite positions of shape (T >= 2, 22, 3), got {tuple(p.shape)}")
        parents = SMPL22_PARENTS[1:]
        bones = p[:, 1:] - p[:, parents]  # (T, 21, 3)
        target = torch.from_numpy(self.target_offsets).norm(dim=-1)  # (22,)
        source = bones[0].norm(dim=-1)
        scale = sum(target[j] for j in LEG_JOINTS) / sum(source[j - 1] for j in LEG_JOINTS)
        # HumanML3D solves IK and runs FK with the target offsets; as its IK maps each
        # bone's rest direction exactly onto the bone, that is: keep directions, set lengths
        directions = F.normalize(bones, dim=-1)
        joints = [p[:, 0] * scale]
        for j, parent in enumerate(parents, start=1):
            joints.append(joints[parent] + directions[:, j - 1] * target[j])
        p = torch.stack(joints, dim=1)
        p[..., 1] -= p[..., 1].min()
        p = p - p[0, 0] * _XZ
        r_hip, l_hip, r_shoulder, l_shoulder = FACE_JOINTS
        across = (p[0, r_hip] - p[0, l_hip]) + (p[0, r_shoulder] - p[0, l_shoulder])
        return quat_apply(_heading(across), p)

    def canonicalize(self, positions: np.ndarray) -> np.ndarray:
        """(T, 22, 3) -> the (T, 22, 3) positions the features describe (HumanML3D's ``new_joints``)."""
        return self._global_positions(positions).numpy()

    def encode(self, clip: Clip) -> tuple[np.ndarray, dict]:
        joints = self._global_positions(clip.positions)  # (T, 22, 3)
        quats = inverse_kinematics(joints, clip.fps)  # (T, 22, 4)
        heading = quats[:, 0]  # (T, 4) turns each frame's facing to +Z (frame 0: the identity)
        root_velocity = quat_apply(heading[1:], joints[1:, 0] - joints[:-1, 0])  # (T-1, 3)
        yaw_velocity = quat_mul(heading[1:], quat_conjugate(heading[:-1]))[:, 2].clamp(-1, 1).asin()
        ric = quat_apply(heading[:, None], joints - joints[:, :1] * _XZ)  # (T, 22, 3)
        local_velocity = quat_apply(heading[:-1, None], joints[1:] - joints[:-1])  # (T-1, 22, 3)
        contacts = foot_contacts(joints, FEET_LEFT + FEET_RIGHT, clip.fps)  # (T-1, 4)
        features = torch.cat(
            [
                yaw_velocity[:, None],
                root_velocity[:, [0, 2]],
                ric[:-1, 0, 1:2],
                ric[:-1, 1:].flatten(1),
                quat_to_6d(quats[:-1, 1:]).flatten(1),
                local_velocity.flatten(1),
                contacts.double(),
            ],
            dim=1,
        )
        return features.numpy().astype(np.float32), {}

    def decode(self, features: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
        """(..., T, 263) -> (..., T, 22, 3): ``recover_from_ric`` (``offsets`` are not needed)."""
        heading, root = _root_heading_position(features)
        ric = features[..., 4:67].unflatten(-1, (21, 3))  # (..., T, 21, 3)
        joints = quat_apply(quat_conjugate(heading)[..., None, :], ric) + (root * _XZ.to(root))[..., None, :]
        return torch.cat([root[..., None, :], joints], dim=-2)

    def positions_from_rotations(
        self,
        features: torch.Tensor,  # (..., T, 263)
        offsets: torch.Tensor | None = None,  # (22, 3); the uniform skeleton (target_offsets) if None
    ) -> torch.Tensor:  # (..., T, 22, 3)
        """FK of the 6D rotations: HumanML3D's ``recover_from_rot``; the positions of ``decode``.

        Frame 0's root rotation is the identity (module docstring), so the heading that the
        features integrate from zero is the IK's root rotation of every frame, and FK of the
        rotations on the uniform skeleton gives ``decode``'s positions.
        """
        heading, root = _root_heading_position(features)
        offsets = features.new_tensor(self.target_offsets) if offsets is None else offsets
        rotations = sixd_to_matrix(features[..., 67:193].unflatten(-1, (21, 6)))  # (..., T, 21, 3, 3)
        root_matrix = quat_to_matrix(heading)  # (..., T, 3, 3)
        joints: list[torch.Tensor | None] = [root] + [None] * 21
        for chain in T2M_CHAINS:
            R = root_matrix
            for a, b in zip(chain[:-1], chain[1:]):
                R = R @ rotations[..., b - 1, :, :]
                joints[b] = joints[a] + (R @ offsets[..., b, :, None]).squeeze(-1)
        return torch.stack(joints, dim=-2)

    def foot_contacts(self, features: torch.Tensor) -> torch.Tensor:
        return features[..., 259:263]

    def contact_features(self) -> tuple[int, ...]:
        return (259, 260, 261, 262)

    def integrated_features(self) -> tuple[int, ...]:
        return (0, 1, 2)  # the yaw rate and the root's XZ velocity

    def heading_features(self) -> tuple[int, ...]:
        return (0,)

    def inpaint(self, features: torch.Tensor, targets: torch.Tensor, stated: torch.Tensor) -> torch.Tensor:
        """The root's height (feature 3) set where a target states it: the one joint coordinate these features
        hold in the world frame (the root's XZ is integrated from velocities, the other joints turn with it)."""
        height = torch.where(stated[..., 0, 1], targets[..., 0, 1], features[..., 3])  # (..., T)
        return torch.cat([features[..., :3], height[..., None], features[..., 4:]], dim=-1)

    def root_from_stance(self, features: torch.Tensor, strength: float = 1.0) -> torch.Tensor:
        """(..., T, 263) -> the features with the root's XZ velocity [1:3] moved ``strength`` of the way to
        the step that keeps the stance foot still, at every step t -> t+1 where a foot joint is in contact
        (its contact feature > 0.5) at both frames. The stance foot is the contact joint that moves least
        in the world under the features' own root step: the foot the body rolls over. Other features are
        unchanged, so the pose, heading and height stay and only the path changes.

        Why: a sampled motion's root velocity and its legs come out of one network unconstrained, and
        guidance extrapolates them apart: the body glides while the stance foot slides (the small recipe's
        walks: the lowest foot moved at 0.4 m/s). A real clip's features satisfy this nearly (its planted
        feet are still up to HumanML3D's loose contact speed): the step keeps 95-99 % of its path.
        """
        heading, root = _root_heading_position(features)  # (..., T, 4), (..., T, 3)
        ric = features[..., 4:67].unflatten(-1, (21, 3))  # (..., T, 21, 3) joints 1..21 around the root
        feet = [j - 1 for j in FEET_LEFT + FEET_RIGHT]
        around = quat_apply(quat_conjugate(heading)[..., None, :], ric[..., feet, :])  # (..., T, 4, 3) world axes
        moved = around[..., 1:, :, :] - around[..., :-1, :, :]  # (..., T-1, 4, 3) each foot joint's step about the root
        contact = features[..., 259:263] > 0.5  # (..., T, 4) in FEET_LEFT + FEET_RIGHT order
        planted = contact[..., 1:, :] & contact[..., :-1, :]  # (..., T-1, 4)
        own_step = (root[..., 1:, :] - root[..., :-1, :])[..., None, :]  # (..., T-1, 1, 3)
        world = (own_step + moved)[..., [0, 2]].norm(dim=-1).masked_fill(~planted, math.inf)  # (..., T-1, 4)
        stance = world.argmin(-1, keepdim=True)  # (..., T-1, 1)
        step = -torch.gather(moved, -2, stance[..., None].expand(*stance.shape, 3)).squeeze(-2)  # (..., T-1, 3)
        velocity = quat_apply(heading[..., 1:, :], step)[..., [0, 2]]  # into frame t+1's heading, as [1:3] is stored
        weight = strength * planted.any(-1, keepdim=True).to(features.dtype)  # (..., T-1, 1)
        out = features.clone()
        out[..., :-1, 1:3] = features[..., :-1, 1:3] + weight * (velocity - features[..., :-1, 1:3])
        return out

    def channel_joints(self) -> np.ndarray:
        """The root's yaw velocity, XZ velocity and height [0:4] are joint 0's; each ric position [4:67] and 6D
        rotation [67:193] its joint's (1..21); each local velocity [193:259] its joint's (0..21); each foot
        contact [259:263] its foot joint's."""
        blocks = ([0] * 4, np.repeat(np.arange(1, 22), 3), np.repeat(np.arange(1, 22), 6),
                  np.repeat(np.arange(22), 3), FEET_LEFT + FEET_RIGHT)
        return np.concatenate([np.asarray(b, dtype=np.int64) for b in blocks])

    def mirror_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The mirror image in HumanML3D's canonical frame (x -> -x, left <-> right joints): the root's
        yaw velocity and sideways velocity flip, its forward velocity and height stay; ric positions
        and local velocities reflect (x flips) and swap joints; the 6D rotations reflect (M R M,
        valid since the rest directions of mirror joints mirror each other) and swap; the left and
        right foot contacts swap."""
        symmetry = check_mirrorable(self)
        index, sign = [0, 1, 2, 3], [-1.0, -1.0, 1.0, 1.0]
        for start, joints, signs in ((4, range(1, 22), REFLECT_X), (67, range(1, 22), SIXD_REFLECT_X),
                                     (193, range(22), REFLECT_X), (259, FEET_LEFT + FEET_RIGHT, (1.0,))):
            block = mirror_block(symmetry, start, joints, signs)
            index, sign = index + block[0], sign + block[1]
        return np.asarray(index), np.asarray(sign)

    def finalize_stats(self, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """HumanML3D's cal_mean_variance: one std per feature group (its mean over the group)."""
        std = np.asarray(std, dtype=np.float64).copy()
        for a, b in GROUPS:
            std[a:b] = std[a:b].mean() / (self.feat_bias if (a, b) in BIASED_GROUPS else 1.0)
        # a group that never varies (no foot contact in a small set) would divide by zero
        return mean.astype(np.float32), np.maximum(std, 1e-4).astype(np.float32)


def _root_heading_position(features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., T, 263) -> heading (..., T, 4) and root position (..., T, 3): ``recover_root_rot_pos``.

    Feature 0 is half the per-frame yaw change (the arcsin of the yaw quaternion's y); its
    running sum is half the heading angle, which starts at zero.
    """
    half = torch.cumsum(F.pad(features[..., :-1, 0], (1, 0)), dim=-1)  # (..., T)
    zero = torch.zeros_like(half)
    heading = torch.stack((half.cos(), zero, half.sin(), zero), dim=-1)  # (..., T, 4)
    step = features[..., :-1, 1:3]  # (..., T-1, 2) root XZ velocity in the heading frame
    step = torch.stack((step[..., 0], torch.zeros_like(step[..., 0]), step[..., 1]), dim=-1)
    step = quat_apply(quat_conjugate(heading[..., 1:, :]), step)
    xz = torch.cumsum(F.pad(step, (0, 0, 1, 0)), dim=-2)  # (..., T, 3)
    root = torch.stack((xz[..., 0], features[..., 3], xz[..., 2]), dim=-1)
    return heading, root
