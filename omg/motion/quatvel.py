"""Habit transfer's representation for any skeleton: local quaternions plus global joint velocities."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from omg.motion.base import Clip, Representation
from omg.motion.maa import fk_offsets, require_rotations
from omg.registry import REPRESENTATIONS
from omg.rotations import quat_normalize


def continuous_quats(q: np.ndarray) -> np.ndarray:
    """(T, J, 4) -> the same rotations with signs chosen to be continuous in time (w >= 0 at t = 0)."""
    sign = np.where(q[0, :, 0] < 0, -1.0, 1.0)[None]  # (1, J)
    steps = np.where((q[1:] * q[:-1]).sum(-1) < 0, -1.0, 1.0)  # (T-1, J)
    sign = sign * np.cumprod(np.concatenate([np.ones_like(sign), steps]), axis=0)
    return q * sign[..., None]


@REPRESENTATIONS.register("quatvel")
class QuatVel(Representation):
    """Per frame J x 4 local quaternions, then J x 3 global joint velocities.

    Row t holds frame t's local rotations (signs continuous in time) and every joint's
    displacement from frame t to t + 1 in world axes, in metres per frame; a clip of T
    frames gives T - 1 rows. ``meta`` keeps the bone offsets and the root's position at
    frame 0 (``root_start``), which ``decode`` needs to put the motion back in place.
    """

    name = "quatvel"
    frames_dropped = 1

    @property
    def dim(self) -> int:
        return self.skeleton.num_joints * 7

    def encode(self, clip: Clip) -> tuple[np.ndarray, dict]:
        rotations, offsets = require_rotations(self, clip)
        positions = np.asarray(clip.positions, dtype=np.float64)  # (T, J, 3)
        T, J = rotations.shape[:2]
        quats = continuous_quats(np.asarray(rotations, dtype=np.float64))[:-1].reshape(T - 1, J * 4)
        velocity = (positions[1:] - positions[:-1]).reshape(T - 1, J * 3)
        meta = {"offsets": offsets.tolist(), "root_start": positions[0, 0].tolist()}
        return np.concatenate([quats, velocity], axis=1).astype(np.float32), meta

    def integrated_features(self) -> tuple[int, ...]:
        J = self.skeleton.num_joints
        return tuple(range(J * 4, J * 4 + 3))  # the root's velocity

    def decode(
        self,
        features: torch.Tensor,  # (..., T', J * 7)
        offsets: torch.Tensor | None = None,  # (J, 3) or (..., J, 3); the skeleton's rest offsets if None
        root_start: torch.Tensor | None = None,  # (3,) or (..., 3) root position at frame 0; origin if None
    ) -> torch.Tensor:  # (..., T', J, 3)
        """Positions of frames 0 .. T'-1: FK of the quaternions from a root trajectory that
        starts at ``root_start`` and moves by the integrated root velocity (row t moves the
        root from frame t to t + 1, so frame t's root is the sum of rows 0 .. t-1)."""
        quats, root = self.rotations_and_root(features, root_start)
        return self.skeleton.forward_kinematics(quats, root, fk_offsets(self.skeleton, offsets, features))

    def rotations_and_root(self, features: torch.Tensor, root_start: torch.Tensor | None = None
                           ) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., T', J * 7) features -> unit local quaternions (..., T', J, 4) and root positions (..., T', 3)."""
        J = self.skeleton.num_joints
        quats = quat_normalize(features[..., : J * 4].unflatten(-1, (J, 4)))  # (..., T', J, 4)
        root_velocity = features[..., J * 4 : J * 4 + 3]  # (..., T', 3) joint 0 comes first
        root = torch.cumsum(F.pad(root_velocity[..., :-1, :], (0, 0, 1, 0)), dim=-2)
        if root_start is not None:
            root = root + torch.as_tensor(root_start, dtype=features.dtype, device=features.device).unsqueeze(-2)
        return quats, root
