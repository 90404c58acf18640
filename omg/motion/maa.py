"""OmniMotionGPT's representation for any skeleton: 6D local rotations plus the root position."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omg import kinematics
from omg.errors import UsageError
from omg.motion.base import Clip, Representation, check_mirrorable, mirror_block
from omg.registry import REPRESENTATIONS
from omg.rotations import REFLECT_X, SIXD_REFLECT_X, quat_to_6d, sixd_to_quat
from omg.skeleton import Skeleton, get_skeleton


def require_rotations(rep: Representation, clip: Clip) -> tuple[np.ndarray, np.ndarray]:
    """The clip's (T, J, 4) local rotations and (J, 3) offsets, checked against ``rep``'s skeleton."""
    J = rep.skeleton.num_joints
    if clip.skeleton.num_joints != J:
        raise UsageError(
            f"clip {clip.id!r} has {clip.skeleton.num_joints} joints ({clip.skeleton.name!r}); "
            f"representation {rep.name!r} is set up for {J} ({rep.skeleton.name!r})"
        )
    if clip.rotations is None or clip.offsets is None:
        return solved_rotations(rep.skeleton, clip)
    return clip.rotations, np.asarray(clip.offsets, dtype=np.float32).reshape(J, 3)


def solved_rotations(skeleton: Skeleton, clip: Clip) -> tuple[np.ndarray, np.ndarray]:
    """(T, J, 4) local rotations and (J, 3) offsets of a clip that has joint positions only (e.g.
    HumanML3D's ``new_joints``): inverse kinematics on the skeleton's bone directions with the
    clip's mean bone lengths, so forward kinematics gives the positions back up to the clip's own
    bone-length jitter (``omg.kinematics``)."""
    positions = torch.as_tensor(np.asarray(clip.positions), dtype=torch.float64)  # (T, J, 3)
    if positions.ndim != 3 or positions.shape[1:] != (skeleton.num_joints, 3) or not torch.isfinite(positions).all():
        raise UsageError(f"clip {clip.id!r} has neither local rotations nor finite {skeleton.name} joint positions "
                         f"(T, {skeleton.num_joints}, 3) to solve them from")
    offsets = kinematics.clip_offsets(skeleton, positions)
    rotations = kinematics.positions_to_rotations(skeleton, positions, offsets)
    return rotations.float().numpy(), offsets.float().numpy()


def fk_offsets(skeleton: Skeleton, offsets: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor:
    """Bone offsets for FK of (..., T, J, ·) inputs: (J, 3) shared, or (..., J, 3) per sample
    (the features' leading dims without time), returned broadcastable to (..., T, J, 3)."""
    if offsets is None:
        offsets = skeleton.rest_offsets
    offsets = torch.as_tensor(offsets, dtype=like.dtype, device=like.device)
    return offsets if offsets.dim() == 2 else offsets.unsqueeze(-3)


@REPRESENTATIONS.register("maa")
class MAA(Representation):
    """Per frame (J + 1) x 6: each joint's local rotation in 6D, then the root position + 3 zeros.

    The 6D rotation is the first two columns of the rotation matrix (``rotations.quat_to_6d``).
    The individual's bone offsets (J, 3) do not change over time; they travel beside the
    features as ``meta["offsets"]`` and come back to ``decode`` for forward kinematics.
    """

    name = "maa"
    frames_dropped = 0

    @property
    def dim(self) -> int:
        return (self.skeleton.num_joints + 1) * 6

    def encode(self, clip: Clip) -> tuple[np.ndarray, dict]:
        rotations, offsets = require_rotations(self, clip)
        T, J = rotations.shape[:2]
        sixd = quat_to_6d(torch.from_numpy(np.asarray(rotations, dtype=np.float64))).reshape(T, J * 6)
        root = np.asarray(clip.positions[:, 0], dtype=np.float64)  # (T, 3)
        features = np.concatenate([sixd.numpy(), root, np.zeros((T, 3))], axis=1)
        return features.astype(np.float32), {"offsets": offsets.tolist()}

    def mirror_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The mirror image across the sagittal plane (x -> -x): every local rotation reflects
        (M R M) onto its mirror joint (the skeleton's ``symmetry``: SMPL-22's or SMAL-35's), the
        root position's x flips; the offsets mirror beside them (``Representation.mirror``)."""
        symmetry = check_mirrorable(self)
        J = self.skeleton.num_joints
        index, sign = mirror_block(symmetry, 0, range(J), SIXD_REFLECT_X)
        return np.asarray(index + list(range(J * 6, J * 6 + 6))), np.asarray(sign + [*REFLECT_X, 1.0, 1.0, 1.0])

    def rotations_and_root(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., T, (J + 1) * 6) features -> local rotations (..., T, J, 4) and root positions (..., T, 3)."""
        J = self.skeleton.num_joints
        rotations = sixd_to_quat(features[..., : J * 6].unflatten(-1, (J, 6)))
        return rotations, features[..., J * 6 : J * 6 + 3]

    def decode(self, features: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
        rotations, root = self.rotations_and_root(features)
        return self.skeleton.forward_kinematics(rotations, root, fk_offsets(self.skeleton, offsets, features))


def root_translation(features: Tensor) -> Tensor:
    """The root translation (..., 3) of maa features (the last token's first 3 numbers)."""
    return features[..., -6:-3]


def maa_from_positions(positions: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Human joint positions (T, 22, 3) -> smpl22 maa features (T, 138) and offsets (22, 3), the
    rotations solved by the representation's IK on the clip's own bone lengths."""
    skeleton = get_skeleton("smpl22")
    clip = Clip(id="human", skeleton=skeleton, fps=fps, positions=np.asarray(positions, dtype=np.float32))
    features, meta = MAA(skeleton).encode(clip)
    return features, np.asarray(meta["offsets"], dtype=np.float32)
