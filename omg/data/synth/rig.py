"""Rotation helpers for keying body channels, an individual's rest pose, and packaging a clip.

Quaternions are (w, x, y, z) float64 torch tensors, as in ``omg.rotations``; angles are radians.
Floor vectors are (x, z) with x to the body's left and z forward; heading is the yaw about +Y,
0 facing +Z, positive turning left (towards +X).
"""

from __future__ import annotations

import numpy as np
import torch

from omg.motion.base import Clip
from omg.rotations import quat_mul
from omg.skeleton import Skeleton


def axis_rotation(axis: str, angle) -> torch.Tensor:
    """(...,) angles -> (..., 4) rotations about the coordinate axis "x", "y" or "z"."""
    angles = torch.as_tensor(np.asarray(angle, dtype=np.float64))
    quat = torch.zeros(angles.shape + (4,), dtype=torch.float64)
    quat[..., 0] = torch.cos(angles / 2)
    quat[..., "xyz".index(axis) + 1] = torch.sin(angles / 2)
    return quat


def compose(*rotations: torch.Tensor) -> torch.Tensor:
    """The product of rotations, left to right (the first is applied last)."""
    out = rotations[0]
    for rotation in rotations[1:]:
        out = quat_mul(out, rotation)
    return out


def rotate_by_heading(heading, x, z):
    """Rotate body-frame floor vectors (x left, z forward) into the world by the heading (yaw about +Y)."""
    cos, sin = np.cos(heading), np.sin(heading)
    return x * cos + z * sin, -x * sin + z * cos


def rest_positions(skeleton: Skeleton, offsets: np.ndarray) -> np.ndarray:
    """(J, 3) rest joint positions relative to the root for this individual's offsets (J, 3)."""
    positions = np.zeros_like(offsets)
    for joint, parent in enumerate(skeleton.parents[1:], 1):
        positions[joint] = positions[parent] + offsets[joint]
    return positions


def make_clip(skeleton, category, index, action, fps, rotations, positions, offsets, texts, labels) -> Clip:
    """Package a solved clip: float32 arrays, the id the shards are keyed by, source "synth"."""
    return Clip(
        id=f"synth_{category}_{index:05d}_{action}", skeleton=skeleton, fps=float(fps),
        positions=positions.numpy().astype(np.float32), rotations=rotations.numpy().astype(np.float32),
        offsets=offsets.astype(np.float32), texts=texts, labels=labels, category=category, source="synth",
    )  # fmt: skip
