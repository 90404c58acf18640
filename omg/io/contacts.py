"""Foot-contact clean-up: planted feet stay where they landed.

Generated motion often lets a planted foot drift a few centimetres (foot skating). Over each
contact, the foot's lowest joint is pinned to its mean ground position; the shift eases in and
out over a few frames, moves the whole foot, and the leg follows by two-bone IK in the plane it
already bends in, so every bone keeps its length and the rest of the body is untouched. A caller
that knows how high each planted foot must stand (``onto_rig``: the rig's sole on its ground) gives
the rise with it, which the same shift carries.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from omg.kinematics import ground_contacts
from omg.skeleton import Skeleton, get_skeleton

# m/s: retargeting's ground-contact rule (omg.kinematics.ground_contacts), but a low foot this slow counts as
# planted (generated feet slide fast)
CLEANUP_SPEED = 1.0
EASE_FRAMES = 2  # frames before landing and after lift-off over which a planted foot's pin eases in and out


def _segments(flags: torch.Tensor) -> list[tuple[int, int]]:
    """[start, end) runs of True in a (T,) bool tensor."""
    edges = torch.diff(torch.cat([flags.new_zeros(1), flags, flags.new_zeros(1)]).int())
    return list(zip(torch.nonzero(edges == 1).flatten().tolist(), torch.nonzero(edges == -1).flatten().tolist()))


def foot_groups(skel: Skeleton) -> list[list[int]]:
    """The feet as connected groups, top joint first: SMPL's (ankle, toe) per side, SMAL's one joint per leg."""
    groups: list[list[int]] = []
    for j in sorted(skel.feet):
        parent_group = next((g for g in groups if skel.parents[j] in g), None)
        parent_group.append(j) if parent_group is not None else groups.append([j])
    return groups


def _descendants(skel: Skeleton, roots: list[int]) -> list[int]:
    out = list(roots)
    for j, p in enumerate(skel.parents):  # parents[j] < j: one pass finds every descendant
        if p in out and j not in out:
            out.append(j)
    return out


def _two_bone(hip: torch.Tensor, knee: torch.Tensor, ankle: torch.Tensor, target: torch.Tensor):
    """(T, 3) each -> (new knee, reached ankle): thigh and shin keep their lengths, the knee stays
    on the side it bent towards; a target beyond reach is approached along the same line."""
    l1, l2 = (knee - hip).norm(dim=-1, keepdim=True), (ankle - knee).norm(dim=-1, keepdim=True)
    to_target = target - hip
    d = to_target.norm(dim=-1, keepdim=True).clamp((l1 - l2).abs() + 1e-6, l1 + l2 - 1e-6)
    u = F.normalize(to_target, dim=-1)
    pole = knee - hip
    pole = F.normalize(pole - (pole * u).sum(-1, keepdim=True) * u, dim=-1)
    a = (l1**2 - l2**2 + d**2) / (2 * d)
    new_knee = hip + a * u + (l1**2 - a**2).clamp_min(0).sqrt() * pole
    return new_knee, new_knee + l2 * F.normalize(hip + d * u - new_knee, dim=-1)


def clean_foot_contacts(
    positions: np.ndarray,  # (T, J, 3) metres, Y up
    skeleton: Skeleton | str,
    fps: float,
    max_speed: float = CLEANUP_SPEED,
    blend: int = EASE_FRAMES,
    rise: np.ndarray | None = None,  # (T, G) metres: per frame, how far each foot group must go up
) -> np.ndarray:
    """Positions with each planted foot pinned over its contact frames (see the module docstring); with
    ``rise``, each group of ``foot_groups`` also moved up by it over its planted frames, and elsewhere where it
    is positive (a foot in the air below the floor)."""
    skel = get_skeleton(skeleton)
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64).clone()  # (T, J, 3)
    T = len(pos)
    if T < 2:
        return pos.numpy().astype(np.float32)
    feet = list(skel.feet)
    height = pos[:, feet, 1]  # (T, F)
    contact = ground_contacts(pos, skel.feet, fps, max_speed=max_speed)  # (T, F)
    for g, group in enumerate(foot_groups(skel)):
        cols = [feet.index(j) for j in group]
        lowest = group[int(height[:, cols].mean(0).argmin())]
        planted = contact[:, cols].any(1)
        shift = torch.zeros(T, 3, dtype=pos.dtype)  # (T, 3) horizontal pin offsets of this foot
        for start, end in _segments(planted):
            xz = pos[start:end, lowest][:, [0, 2]]
            shift[start:end, [0, 2]] = xz.mean(0) - xz
            if rise is not None:
                shift[start:end, 1] = torch.as_tensor(rise[start:end, g], dtype=pos.dtype)
            for k in range(1, blend + 1):  # ease the offset in before landing and out after lift-off
                for frame, edge in ((start - k, start), (end - 1 + k, end - 1)):
                    if 0 <= frame < T and not planted[frame]:
                        shift[frame] = shift[edge] * (1 - k / (blend + 1))
        if rise is not None:
            up = torch.as_tensor(rise[:, g], dtype=pos.dtype).clamp_min(0.0)
            shift[~planted, 1] = torch.maximum(shift[~planted, 1], up[~planted])
        top = group[0]
        knee = skel.parents[top]
        hip = skel.parents[knee] if knee >= 0 else -1
        if hip < 0:  # no leg to bend: the foot alone cannot move without stretching a bone
            continue
        new_knee, reached = _two_bone(pos[:, hip], pos[:, knee], pos[:, top], pos[:, top] + shift)
        moved = _descendants(skel, [top])
        pos[:, moved] += (reached - pos[:, top])[:, None]
        pos[:, knee] = new_knee
    return pos.numpy().astype(np.float32)
