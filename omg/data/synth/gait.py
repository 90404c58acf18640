"""Feet and legs: footfall schedules, foot-tip targets along the root path, and two-bone leg IK.

A leg's foot tip is planted at a fixed world point during stance and arcs to the next footprint
during swing; the legs then reach for those tips by analytic two-bone IK, with the root lowered
just enough that every planted leg can reach. Labelled contacts are therefore exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from omg.data.synth.curves import bump, lower_envelope, smoothstep
from omg.data.synth.rig import rotate_by_heading
from omg.data.synth.timeline import RootPath
from omg.rotations import matrix_to_quat, quat_apply, quat_conjugate, quat_mul
from omg.skeleton import Skeleton

GRAVITY = 9.81  # m/s^2


# ----------------------------------------------------------------------------- footfalls


@dataclass(frozen=True)
class Gait:
    """A footfall pattern: leg l touches down whenever ``frequency_hz * t - lags[l]`` crosses an integer."""

    frequency_hz: float  # gait cycles per second
    duty_factor: float  # fraction of a cycle each foot is planted
    lags: tuple[float, ...]  # per leg, touchdown lag in cycles
    lift_m: float  # swing apex of the foot tip
    roll_rad: tuple[float, ...]  # per leg, heel-off / paw-fold angle at lift-off

    def phase(self, seconds: np.ndarray) -> np.ndarray:
        """(N,) seconds -> (N, L) cycles: the integer part counts steps, the fraction is the cycle position."""
        return self.frequency_hz * seconds[:, None] - np.asarray(self.lags)


@dataclass(frozen=True, eq=False)
class FootTargets:
    """Where each foot tip is on every clip frame, and how the foot is turned."""

    tips: np.ndarray  # (T, L, 3) world positions of the foot tips
    yaw: np.ndarray  # (T, L) foot heading (rad), blended between footprints during swing
    pitch: np.ndarray  # (T, L) heel-off / paw fold (rad)
    contact: np.ndarray  # (T, L) bool, planted


def foot_targets(padded_seconds, frames: slice, phase, gait: Gait, activity, path: RootPath, neutral) -> FootTargets:
    """Foot-tip targets from the footfall schedule.

    phase (N, L) on the padded grid ``padded_seconds`` (N,); a footprint is where the body's
    neutral foot position (neutral (L, 2), body-frame x, z) lies at mid-stance, so footprints
    follow any path. ``activity`` (N,) in [0, 1] scales lift and heel-off (0: standing still).
    """
    clip_phase, duty = phase[frames], gait.duty_factor  # (T, L)
    step = np.floor(clip_phase)  # which step each foot is on
    cycle_position = clip_phase - step  # [0, duty): stance, [duty, 1): swing

    def footprint(step_index):  # (T, L) -> x, z, heading (T, L) of that step's planted foot
        mid_stance_s = np.stack(
            [
                np.interp(step_index[:, leg] + duty / 2, phase[:, leg], padded_seconds)
                for leg in range(clip_phase.shape[1])
            ],
            1,
        )
        x, z, heading = path.at(mid_stance_s)
        dx, dz = rotate_by_heading(heading, neutral[:, 0], neutral[:, 1])
        return x + dx, z + dz, heading

    (x_from, z_from, yaw_from), (x_to, z_to, yaw_to) = footprint(step), footprint(step + 1)
    swing = np.clip((cycle_position - duty) / (1 - duty), 0.0, 1.0)  # swing progress, 0 throughout stance
    blend, foot_activity = smoothstep(swing), activity[frames][:, None]
    # a foot that has somewhere to go lifts, even while the gait is only starting
    half_step_m = 0.5 * np.hypot(x_to - x_from, z_to - z_from)
    apex_m = np.maximum(gait.lift_m * foot_activity, np.minimum(gait.lift_m, half_step_m))
    tips = np.stack(
        (x_from + (x_to - x_from) * blend, apex_m * np.sin(np.pi * swing), z_from + (z_to - z_from) * blend), -1
    )
    # heel-off over the last 40% of stance (pivoting on the planted tip), unrolled in early swing
    roll_profile = np.where(
        cycle_position < duty, smoothstep((cycle_position / duty - 0.6) / 0.4), 1 - smoothstep(swing / 0.5)
    )
    pitch = np.asarray(gait.roll_rad) * foot_activity * roll_profile
    contact = (cycle_position < duty) | (apex_m < 1e-3)
    return FootTargets(tips, yaw_from + (yaw_to - yaw_from) * blend, pitch, contact)


def jump_phase(padded_seconds, takeoffs_s, flight_s, duty):
    """(N,) gait phase for discrete jumps: stance k ends at takeoff k, flight k ends at landing k.

    Used instead of ``Gait.phase`` so that ``foot_targets`` plants the feet between jumps and
    swings them (ballistically, with the root) during each flight.
    """
    knot_seconds = (
        [padded_seconds[0] - 1.0]
        + [moment for takeoff in takeoffs_s for moment in (takeoff, takeoff + flight_s)]
        + [padded_seconds[-1] + 1.0]
    )
    knot_phases = (
        [0.0] + [p for jump in range(len(takeoffs_s)) for p in (jump + duty, jump + 1.0)] + [len(takeoffs_s) + duty]
    )
    return np.interp(padded_seconds, knot_seconds, knot_phases)


def jump_root(padded_seconds, takeoffs_s, flight_s, crouch_m, distance_m, time_scale):
    """Root height offset (N,) (crouch, ballistic flight, landing) and forward speed (N,) of jumps.

    ``time_scale`` stretches the crouches of larger bodies (1 for people)."""
    apex_m, push_half_width_s = GRAVITY * flight_s**2 / 8, flight_s / 2 + 0.25 * time_scale
    height_offset, forward_speed = np.zeros_like(padded_seconds), np.zeros_like(padded_seconds)
    for takeoff in takeoffs_s:
        flight_progress = (padded_seconds - takeoff) / flight_s
        height_offset += np.where(
            (flight_progress > 0) & (flight_progress < 1), 4 * apex_m * flight_progress * (1 - flight_progress), 0.0
        )
        height_offset -= crouch_m * (
            bump(padded_seconds, takeoff - 0.22 * time_scale, 0.22 * time_scale)
            + bump(padded_seconds, takeoff + flight_s + 0.2 * time_scale, 0.22 * time_scale)
        )
        push = bump(padded_seconds, takeoff + flight_s / 2, push_half_width_s)
        forward_speed += distance_m * push / push_half_width_s  # integrates to `distance_m`
    return height_offset, forward_speed


# ----------------------------------------------------------------------------- legs and inverse kinematics


@dataclass(frozen=True)
class Leg:
    joints: tuple[int, int, int, int]  # anchor (hip/shoulder), mid (knee/elbow), end (ankle/wrist), tip
    pole: tuple[float, float, float]  # where the mid joint points, in the anchor parent's frame


HUMAN_LEGS = (Leg((1, 4, 7, 10), (0.1, 0.0, 1.0)), Leg((2, 5, 8, 11), (-0.1, 0.0, 1.0)))  # left, right: knees forward
# LF, LH, RF, RH: the order of SMAL35.feet; elbows point back, stifles forward
ANIMAL_LEGS = (
    Leg((7, 8, 9, 10), (0.0, 0.0, -1.0)), Leg((17, 18, 19, 20), (0.0, 0.0, 1.0)),
    Leg((11, 12, 13, 14), (0.0, 0.0, -1.0)), Leg((21, 22, 23, 24), (0.0, 0.0, 1.0)),
)  # fmt: skip


def two_bone(anchor, target, upper_length, lower_length, pole):
    """Mid and end positions of a chain anchor -> mid -> end with bone lengths (..., 1) reaching for
    ``target`` (..., 3); the mid joint bends towards ``pole`` (..., 3). An unreachable target is
    approached as closely as the chain allows."""
    to_target = target - anchor
    direction = F.normalize(to_target, dim=-1)
    distance = torch.minimum(
        torch.maximum(to_target.norm(dim=-1, keepdim=True), (upper_length - lower_length).abs() + 1e-4),
        upper_length + lower_length - 1e-4,
    )
    along = (upper_length**2 - lower_length**2 + distance**2) / (2 * distance)  # mid joint's projection
    out = (upper_length**2 - along**2).clamp_min(0.0).sqrt()  # and its distance from the line
    bend = F.normalize(pole - (pole * direction).sum(-1, keepdim=True) * direction, dim=-1)
    return anchor + along * direction + out * bend, anchor + distance * direction


def orthonormal_frame(primary, side):
    """(..., 3, 3) orthonormal frame with ``primary`` as the first axis and ``side`` (orthogonalised) as the second."""
    first = F.normalize(primary, dim=-1)
    second = F.normalize(side - (side * first).sum(-1, keepdim=True) * first, dim=-1)
    return torch.stack((first, second, torch.cross(first, second, dim=-1)), -1)


def aim(rest_bone, bone, side):
    """Global rotation taking a rest bone (lateral axis +X) onto ``bone`` with lateral axis ``side``."""
    rest_frame = orthonormal_frame(
        rest_bone.expand_as(bone), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand_as(bone)
    )
    return matrix_to_quat(orthonormal_frame(bone, side) @ rest_frame.transpose(-1, -2))


def solve_legs(
    skeleton: Skeleton, offsets, legs, rotations, root_xz, root_height, tips, end_rotations, contact, poles, smoothing
):
    """Fill the legs' rotations by two-bone IK, with the root as high as the planted feet allow.

    rotations (T, J, 4) local, legs at rest (filled in place); root_xz (T, 2); root_height (T,)
    nominal; tips (T, L, 3) foot-tip targets; end_rotations (T, L, 4) world rotation of each end
    joint (ankle / wrist / hock); contact (T, L); poles (T, L, 3); smoothing: frames of the root
    height's lower envelope. Returns rotations (T, J, 4), positions (T, J, 3).
    """
    offsets_t, num_frames = torch.as_tensor(offsets), rotations.shape[0]
    anchor, mid, end, tip = (list(joints) for joints in zip(*(leg.joints for leg in legs)))
    # world rotation and root-relative position of the anchors' ancestors: the body alone sets them
    world, relative, body_joints = {}, {}, set()
    for joint in anchor:
        while joint >= 0:
            body_joints.add(joint)
            joint = skeleton.parents[joint]
    for joint in sorted(body_joints):
        parent = skeleton.parents[joint]
        world[joint] = rotations[:, joint] if parent < 0 else quat_mul(world[parent], rotations[:, joint])
        relative[joint] = (
            torch.zeros(num_frames, 3, dtype=torch.float64)
            if parent < 0
            else relative[parent] + quat_apply(world[parent], offsets_t[joint])
        )
    anchor_parent = torch.stack([world[skeleton.parents[a]] for a in anchor], 1)  # (T, L, 4)
    anchor_relative = torch.stack([relative[a] for a in anchor], 1)  # (T, L, 3)
    ends = tips - quat_apply(end_rotations, offsets_t[tip])  # (T, L, 3) ankle / wrist targets
    upper_length = offsets_t[mid].norm(dim=-1, keepdim=True)  # (L, 1)
    lower_length = offsets_t[end].norm(dim=-1, keepdim=True)  # (L, 1)
    # highest root for which every planted leg reaches: (root_y + rel_y - end_y)^2 + horizontal^2 <= reach^2
    horizontal2 = (root_xz[:, None] + anchor_relative[..., [0, 2]] - ends[..., [0, 2]]).square().sum(-1)
    reach = 0.985 * (upper_length + lower_length)[:, 0]
    highest = ends[..., 1] - anchor_relative[..., 1] + (reach**2 - horizontal2).clamp_min(1e-4).sqrt()
    highest = torch.where(contact, highest, torch.inf).amin(-1).numpy()
    root_y = torch.as_tensor(lower_envelope(np.minimum(root_height, highest), smoothing))
    root = torch.stack((root_xz[:, 0], root_y, root_xz[:, 1]), -1)
    anchor_position = root[:, None] + anchor_relative
    mid_position, end_position = two_bone(
        anchor_position, ends, upper_length, lower_length, quat_apply(anchor_parent, poles)
    )
    side = quat_apply(anchor_parent, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    anchor_world = aim(offsets_t[mid], mid_position - anchor_position, side)
    mid_world = aim(offsets_t[end], end_position - mid_position, side)
    rotations[:, anchor] = quat_mul(quat_conjugate(anchor_parent), anchor_world)
    rotations[:, mid] = quat_mul(quat_conjugate(anchor_world), mid_world)
    rotations[:, end] = quat_mul(quat_conjugate(mid_world), end_rotations)
    return rotations, skeleton.forward_kinematics(rotations, root, offsets_t)
