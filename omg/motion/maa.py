"""OmniMotionGPT's representation for any skeleton: 6D local rotations plus the root position."""

from __future__ import annotations

import numpy as np
import torch

from omg.errors import UsageError
from omg.motion.base import Clip, Representation
from omg.registry import REPRESENTATIONS
from omg.rotations import quat_to_6d, sixd_to_quat
from omg.skeleton import Skeleton


def require_rotations(rep: Representation, clip: Clip) -> tuple[np.ndarray, np.ndarray]:
    """The clip's (T, J, 4) local rotations and (J, 3) offsets, checked against ``rep``'s skeleton."""
    J = rep.skeleton.num_joints
    if clip.skeleton.num_joints != J:
        raise UsageError(
            f"clip {clip.id!r} has {clip.skeleton.num_joints} joints ({clip.skeleton.name!r}); "
            f"representation {rep.name!r} is set up for {J} ({rep.skeleton.name!r})"
        )
    if clip.rotations is None or clip.offsets is None:
        raise UsageError(
            f"representation {rep.name!r} needs local joint rotations and bone offsets, and clip "
            f"{clip.id!r} has none; use a source that provides them (BVH, synthetic data)"
        )
    return clip.rotations, np.asarray(clip.offsets, dtype=np.float32).reshape(J, 3)


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

    def decode(self, features: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
        J = self.skeleton.num_joints
        rotations = sixd_to_quat(features[..., : J * 6].unflatten(-1, (J, 6)))  # (..., T, J, 4)
        root = features[..., J * 6 : J * 6 + 3]  # (..., T, 3)
        return self.skeleton.forward_kinematics(rotations, root, fk_offsets(self.skeleton, offsets, features))
