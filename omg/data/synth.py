"""Procedural labelled motion: the embedded mini dataset (humans on smpl22, quadrupeds on smal35).

A clip is built the way an animator keys it: a root path on the floor, a footfall schedule
(stance: the foot tip is planted at a fixed world point; swing: an arc to the next footprint),
body channels (lean, sway, arm swing, spine flex, tail) and analytic two-bone IK that puts each
leg of this individual on its target. Positions are the forward kinematics of the rotations, so
bone lengths are constant and labelled contacts are exact by construction. Everything is
vectorised over frames; one ``numpy.random.Generator`` seeded by (seed, kind, index) drives
each clip, so a clip depends only on its own index.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
import torch
import torch.nn.functional as F

from omg.errors import UsageError
from omg.motion.base import Clip
from omg.rotations import matrix_to_quat, quat_apply, quat_between, quat_conjugate, quat_identity, quat_mul
from omg.skeleton import SMAL35, SMPL22, Skeleton

GRAVITY = 9.81
HUMAN_ACTIONS = ("walk", "run", "jump", "turn", "wave", "kick", "sit", "crouch", "punch", "idle")
ANIMAL_ACTIONS = ("walk", "trot", "gallop", "jump", "sit", "lie", "idle", "turn")
F64 = torch.float64


# ----------------------------------------------------------------------------- small helpers


def _ss(x):
    """Smoothstep on [0, 1], clamped outside."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _window(t, t0, t1, ramp):
    """1 on [t0, t1] with smooth ramps of ``ramp`` seconds outside it."""
    return _ss((t - t0 + ramp) / ramp) * _ss((t1 - t + ramp) / ramp)


def _bump(t, center, half_width):
    """Raised cosine, 1 at ``center`` and exactly 0 beyond ``half_width``."""
    x = np.clip((t - center) / half_width, -1.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def _rot(axis: str, angle) -> torch.Tensor:
    """(...,) angles -> (..., 4) rotations about a coordinate axis."""
    a = torch.as_tensor(np.asarray(angle, dtype=np.float64))
    q = torch.zeros(a.shape + (4,), dtype=F64)
    q[..., 0] = torch.cos(a / 2)
    q[..., "xyz".index(axis) + 1] = torch.sin(a / 2)
    return q


def _qmul(*qs: torch.Tensor) -> torch.Tensor:
    out = qs[0]
    for q in qs[1:]:
        out = quat_mul(out, q)
    return out


def _yaw_apply(heading, x, z):
    """Rotate body-frame floor vectors (x left, z forward) by the heading (yaw about +Y)."""
    c, s = np.cos(heading), np.sin(heading)
    return x * c + z * s, -x * s + z * c


def _below(y: np.ndarray, r: int) -> np.ndarray:
    """A smooth curve that never exceeds ``y``: min-filter of radius r, then a window of radius r."""
    pad = np.pad(y, r, mode="edge")
    eroded = np.lib.stride_tricks.sliding_window_view(pad, 2 * r + 1).min(-1)
    kernel = np.hanning(2 * r + 3)[1:-1]
    return np.convolve(np.pad(eroded, r, mode="edge"), kernel / kernel.sum(), mode="valid")


def _captions(rng, subjects, predicates, *groups, suffixes=("",)) -> list[str]:
    """2-3 distinct captions: subject, predicate, up to two modifiers (one per group) and a suffix."""
    pick = lambda xs: xs[rng.integers(len(xs))]  # noqa: E731
    n, out = int(rng.integers(2, 4)), []
    for _ in range(20):
        mods = [m for m in (pick(g) for g in groups) if m]
        mods = [mods[i] for i in rng.permutation(len(mods))[:2]]  # more than two reads like a list
        text = " ".join(w for w in (pick(subjects), pick(predicates), *mods, pick(suffixes)) if w) + "."
        if text not in out:
            out.append(text)
        if len(out) == n:
            break
    return out


# ----------------------------------------------------------------------------- root path and footfalls


@dataclass(frozen=True)
class Gait:
    """A footfall pattern: leg l touches down whenever ``freq * t - offsets[l]`` crosses an integer."""

    freq: float  # cycles per second
    duty: float  # fraction of a cycle each foot is planted
    offsets: tuple[float, ...]  # per leg, touchdown lag in cycles
    lift: float  # swing apex of the foot tip (m)
    roll: tuple[float, ...]  # per leg, heel-off / paw-fold angle at lift-off (rad)

    def phase(self, t: np.ndarray) -> np.ndarray:  # (N,) -> (N, L)
        return self.freq * t[:, None] - np.asarray(self.offsets)


@dataclass(frozen=True)
class _Path:
    """The root's floor trajectory on a time grid that extends past both ends of the clip."""

    t: np.ndarray  # (N,)
    x: np.ndarray  # (N,)
    z: np.ndarray  # (N,)
    heading: np.ndarray  # (N,) yaw, 0 = facing +Z, positive turns left (towards +X)

    @classmethod
    def integrate(cls, t, zero: int, velocity, yaw_rate) -> _Path:
        """velocity (N, 2) in the body frame (x left, z forward), yaw_rate (N,); origin at t[zero]."""
        dt = t[1] - t[0]
        heading = np.cumsum(yaw_rate) * dt
        heading -= heading[zero]
        vx, vz = _yaw_apply(heading, velocity[:, 0], velocity[:, 1])
        x, z = np.cumsum(vx) * dt, np.cumsum(vz) * dt
        return cls(t, x - x[zero], z - z[zero], heading)

    def at(self, tq):
        return tuple(np.interp(tq, self.t, v) for v in (self.x, self.z, self.heading))


def _feet(te, frames, phase, gait: Gait, activity, path: _Path, neutral):
    """Foot-tip targets from the footfall schedule.

    phase (N, L) on the extended grid ``te``; a footprint is where the body's neutral foot
    position (neutral (L, 2), body-frame x, z) lies at mid-stance, so footprints follow any
    path. ``activity`` (N,) in [0, 1] scales lift and heel-off (0: standing still).
    Returns tips (T, L, 3), yaw (T, L), pitch (T, L) and contact (T, L).
    """
    ph, d = phase[frames], gait.duty
    k = np.floor(ph)
    u = ph - k

    def footprint(kk):
        tm = np.stack([np.interp(kk[:, i] + d / 2, phase[:, i], te) for i in range(ph.shape[1])], 1)
        x, z, h = path.at(tm)
        dx, dz = _yaw_apply(h, neutral[:, 0], neutral[:, 1])
        return x + dx, z + dz, h

    (x0, z0, h0), (x1, z1, h1) = footprint(k), footprint(k + 1)
    s = np.clip((u - d) / (1 - d), 0.0, 1.0)  # swing progress
    w, a = _ss(s), activity[frames][:, None]
    # a foot that has somewhere to go lifts, even while the gait is only starting
    amp = np.maximum(gait.lift * a, np.minimum(gait.lift, 0.5 * np.hypot(x1 - x0, z1 - z0)))
    tips = np.stack((x0 + (x1 - x0) * w, amp * np.sin(np.pi * s), z0 + (z1 - z0) * w), -1)
    # heel-off over the last 40% of stance (pivoting on the planted tip), unrolled in early swing
    pitch = np.asarray(gait.roll) * a * np.where(u < d, _ss((u / d - 0.6) / 0.4), 1 - _ss(s / 0.5))
    return tips, h0 + (h1 - h0) * w, pitch, (u < d) | (amp < 1e-3)


def _jump_phase(te, takeoffs, flight, duty):
    """(N,) phase for discrete jumps: stance k ends at takeoff k, flight k ends at landing k."""
    knots_t = [te[0] - 1.0] + [t for to in takeoffs for t in (to, to + flight)] + [te[-1] + 1.0]
    knots_p = [0.0] + [p for k in range(len(takeoffs)) for p in (k + duty, k + 1.0)] + [len(takeoffs) + duty]
    return np.interp(te, knots_t, knots_p)


def _jump_root(te, takeoffs, flight, crouch, distance, ts):
    """Root height offset (N,) (crouch, ballistic flight, landing) and forward speed (N,) of jumps."""
    apex, hw = GRAVITY * flight**2 / 8, flight / 2 + 0.25 * ts
    dy, vz = np.zeros_like(te), np.zeros_like(te)
    for to in takeoffs:
        x = (te - to) / flight
        dy += np.where((x > 0) & (x < 1), 4 * apex * x * (1 - x), 0.0)
        dy -= crouch * (_bump(te, to - 0.22 * ts, 0.22 * ts) + _bump(te, to + flight + 0.2 * ts, 0.22 * ts))
        vz += distance * _bump(te, to + flight / 2, hw) / hw  # integrates to `distance`
    return dy, vz


# ----------------------------------------------------------------------------- inverse kinematics


@dataclass(frozen=True)
class _Leg:
    joints: tuple[int, int, int, int]  # anchor (hip/shoulder), mid (knee/elbow), end (ankle/wrist), tip
    pole: tuple[float, float, float]  # where the mid joint points, in the anchor parent's frame


HUMAN_LEGS = (_Leg((1, 4, 7, 10), (0.1, 0.0, 1.0)), _Leg((2, 5, 8, 11), (-0.1, 0.0, 1.0)))
# LF, LH, RF, RH: the order of SMAL35.feet; elbows point back, stifles forward
ANIMAL_LEGS = (
    _Leg((7, 8, 9, 10), (0.0, 0.0, -1.0)), _Leg((17, 18, 19, 20), (0.0, 0.0, 1.0)),
    _Leg((11, 12, 13, 14), (0.0, 0.0, -1.0)), _Leg((21, 22, 23, 24), (0.0, 0.0, 1.0)),
)  # fmt: skip


def _two_bone(a, c, l1, l2, pole):
    """Mid and end positions of a chain a -> b -> c of bone lengths l1, l2 (..., 1) reaching for c."""
    d = c - a
    n = F.normalize(d, dim=-1)
    dist = torch.minimum(torch.maximum(d.norm(dim=-1, keepdim=True), (l1 - l2).abs() + 1e-4), l1 + l2 - 1e-4)
    x = (l1**2 - l2**2 + dist**2) / (2 * dist)
    h = (l1**2 - x**2).clamp_min(0.0).sqrt()
    m = F.normalize(pole - (pole * n).sum(-1, keepdim=True) * n, dim=-1)
    return a + x * n + h * m, a + dist * n


def _frame(d, side):
    """(..., 3, 3) orthonormal frame with d as the first axis and side (orthogonalised) as the second."""
    e1 = F.normalize(d, dim=-1)
    e2 = F.normalize(side - (side * e1).sum(-1, keepdim=True) * e1, dim=-1)
    return torch.stack((e1, e2, torch.cross(e1, e2, dim=-1)), -1)


def _aim(rest_bone, bone, side):
    """Global rotation taking a rest bone (lateral axis +X) onto ``bone`` with lateral axis ``side``."""
    rest = _frame(rest_bone.expand_as(bone), torch.tensor([1.0, 0.0, 0.0], dtype=F64).expand_as(bone))
    return matrix_to_quat(_frame(bone, side) @ rest.transpose(-1, -2))


def _solve_legs(skel: Skeleton, off, legs, rot, root_xz, height, tips, foot_q, contact, poles, radius):
    """Fill the legs' rotations by two-bone IK, with the root as high as the planted feet allow.

    rot (T, J, 4) local rotations, legs at rest; root_xz (T, 2); height (T,) nominal root height;
    tips (T, L, 3) foot-tip targets; foot_q (T, L, 4) world rotation of each end joint (ankle /
    wrist / hock); contact (T, L); poles (T, L, 3). Returns rotations (T, J, 4), positions (T, J, 3).
    """
    off_t, T = torch.as_tensor(off), rot.shape[0]
    anchor, mid, end, tip = (list(j) for j in zip(*(leg.joints for leg in legs)))
    # world rotation and root-relative position of the anchors' ancestors: the body alone sets them
    glob, rel, todo = {}, {}, set()
    for j in anchor:
        while j >= 0:
            todo.add(j)
            j = skel.parents[j]
    for j in sorted(todo):
        p = skel.parents[j]
        glob[j] = rot[:, j] if p < 0 else quat_mul(glob[p], rot[:, j])
        rel[j] = torch.zeros(T, 3, dtype=F64) if p < 0 else rel[p] + quat_apply(glob[p], off_t[j])
    parent = torch.stack([glob[skel.parents[a]] for a in anchor], 1)  # (T, L, 4)
    rel_a = torch.stack([rel[a] for a in anchor], 1)  # (T, L, 3)
    ends = tips - quat_apply(foot_q, off_t[tip])  # (T, L, 3) ankle / wrist targets
    l1, l2 = off_t[mid].norm(dim=-1, keepdim=True), off_t[end].norm(dim=-1, keepdim=True)  # (L, 1)
    # highest root for which every planted leg reaches: (root_y + rel_y - end_y)^2 + dh^2 <= reach^2
    dh2 = (root_xz[:, None] + rel_a[..., [0, 2]] - ends[..., [0, 2]]).square().sum(-1)
    reach = 0.985 * (l1 + l2)[:, 0]
    y_max = ends[..., 1] - rel_a[..., 1] + (reach**2 - dh2).clamp_min(1e-4).sqrt()
    y_max = torch.where(contact, y_max, torch.inf).amin(-1).numpy()
    y = torch.as_tensor(_below(np.minimum(height, y_max), radius))
    root = torch.stack((root_xz[:, 0], y, root_xz[:, 1]), -1)
    pos_a = root[:, None] + rel_a
    pos_b, pos_c = _two_bone(pos_a, ends, l1, l2, quat_apply(parent, poles))
    side = quat_apply(parent, torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    qa, qm = _aim(off_t[mid], pos_b - pos_a, side), _aim(off_t[end], pos_c - pos_b, side)
    rot[:, anchor] = quat_mul(quat_conjugate(parent), qa)
    rot[:, mid] = quat_mul(quat_conjugate(qa), qm)
    rot[:, end] = quat_mul(quat_conjugate(qm), foot_q)
    return rot, skel.forward_kinematics(rot, root, off_t)


def _rest_rel(skel: Skeleton, off: np.ndarray) -> np.ndarray:
    """(J, 3) rest joint positions relative to the root for this individual's offsets."""
    pos = np.zeros_like(off)
    for j, p in enumerate(skel.parents[1:], 1):
        pos[j] = pos[p] + off[j]
    return pos


# ----------------------------------------------------------------------------- humans


@dataclass(frozen=True)
class Style:
    """How a mood changes locomotion and posture."""

    speed: float = 1.0
    cadence: float = 1.0
    bounce: float = 0.015  # vertical bob (m)
    lean: float = 0.05  # forward trunk lean (rad)
    lift: float = 1.0
    swing: float = 1.0  # arm swing
    crouch: float = 0.0  # pelvis lowered (m)
    head: float = 0.0  # head pitch, + looks down (rad)


STYLES = {
    "neutral": Style(),
    "happy": Style(speed=1.1, cadence=1.15, bounce=0.045, lean=0.0, lift=1.3, swing=1.6, head=-0.1),
    "tired": Style(speed=0.7, cadence=0.85, bounce=0.008, lean=0.3, lift=0.6, swing=0.4, crouch=0.03, head=0.35),
    "sneaky": Style(speed=0.6, cadence=0.8, bounce=0.005, lean=0.35, lift=0.8, swing=0.4, crouch=0.12, head=-0.2),
    "proud": Style(speed=1.0, cadence=0.95, bounce=0.02, lean=-0.08, lift=1.1, swing=1.3, head=-0.12),
    "striding": Style(speed=1.15, cadence=0.85, bounce=0.02, lift=1.2, swing=1.3),  # long steps
}
STYLE_WORDS = {
    "neutral": ("",),
    "happy": ("happily", "with a bounce in their step", "cheerfully"),
    "tired": ("wearily", "as if exhausted", "with slumped shoulders"),
    "sneaky": ("sneakily", "crouched low", "stealthily"),
    "proud": ("proudly", "with a confident stride", "with the chest held high"),
    "striding": ("with long strides", "taking big steps", "with big strides"),
}
PEOPLE = ("a person", "someone", "a man", "a woman", "the person", "a human")
SPEED_WORDS = {
    "slow": ("slowly", "at a slow pace", ""), "normal": ("",), "fast": ("quickly", "briskly", "at a fast pace"),
}  # fmt: skip
HANG = (0.05, 0.15, 0.0, 0.2)  # arm channels at rest: flexion, abduction, twist, elbow (rad)


def _human_offsets(rng) -> tuple[np.ndarray, float]:
    """This individual's bone offsets (overall 0.9-1.1 height, a little segment variation) and scale."""
    scale = rng.uniform(0.9, 1.1)
    off = SMPL22.rest_offsets.astype(np.float64) * scale
    off[[4, 5, 7, 8]] *= rng.uniform(0.96, 1.04)  # thighs and shins
    off[[18, 19, 20, 21]] *= rng.uniform(0.95, 1.05)  # arms
    off[[1, 2, 13, 14, 16, 17], 0] *= rng.uniform(0.92, 1.08)  # hip and shoulder width
    off[0] = 0.0
    off[0, 1] = -_rest_rel(SMPL22, off)[:, 1].min()  # rest soles on the floor
    return off, scale


def _human_rotations(off, heading, pelvis, spine, head, arms) -> torch.Tensor:
    """(T, 22, 4) body rotations (legs at rest) from channels: pelvis/spine (T, 3) yaw, pitch, roll
    (+pitch leans forward), head (T, 2) yaw, pitch, arms (T, 2, 4) flexion, abduction, twist, elbow."""
    rot = quat_identity((len(heading), 22), F64)
    rot[:, 0] = _qmul(_rot("y", heading + pelvis[:, 0]), _rot("x", pelvis[:, 1]), _rot("z", pelvis[:, 2]))
    for j in (3, 6, 9):
        rot[:, j] = _qmul(_rot("y", spine[:, 0] / 3), _rot("x", spine[:, 1] / 3), _rot("z", spine[:, 2] / 3))
    for j in (12, 15):
        rot[:, j] = _qmul(_rot("y", head[:, 0] / 2), _rot("x", head[:, 1] / 2))
    down = torch.tensor([0.0, -1.0, 0.0], dtype=F64)
    for side, (sh, el, wr) in enumerate(((16, 18, 20), (17, 19, 21))):
        sign, (f, a, r, e) = 1 - 2 * side, arms[:, side].T
        # the arm is posed from hanging straight down; the rest T-pose is rotated there first
        hang_upper = quat_between(torch.as_tensor(off[el]), down)
        hang_fore = quat_between(torch.as_tensor(off[wr]), down)
        rot[:, sh] = _qmul(_rot("x", -f), _rot("z", sign * a), _rot("y", sign * r), hang_upper)
        rot[:, el] = _qmul(quat_conjugate(hang_upper), _rot("x", -e), hang_fore)
    return rot


def _human(rng, index: int, fps: float) -> tuple[Clip, np.ndarray]:
    """Human clip ``index``: sample the action's parameters, key its channels, solve the legs."""
    action = HUMAN_ACTIONS[index % len(HUMAN_ACTIONS)]
    pick = lambda xs: xs[rng.integers(len(xs))]  # noqa: E731
    U = rng.uniform
    off, s = _human_offsets(rng)
    rest = _rest_rel(SMPL22, off)
    h0 = 0.985 * off[0, 1]  # standing root height, knees barely bent
    neutral = rest[[10, 11]][:, [0, 2]] * (0.85, 1.0)  # (2, 2) foot tips under the standing body

    # the clip's duration first, then every channel as a function of time
    D = {"walk": U(3, 10), "run": U(2.5, 7), "idle": U(2, 8)}.get(action, 0.0)
    moods = {"walk": tuple(STYLES)[1:], "run": ("happy", "tired"), "idle": ("tired", "proud")}.get(action, ())
    style = pick(("neutral",) * 3 + moods)
    st, labels = STYLES[style], {"action": action, "style": style}
    plan = {}  # action-specific timing, used below
    if action == "jump":
        n, t_f, T_c = int(rng.integers(1, 4)), U(0.3, 0.42), U(1.0, 1.3)
        plan = dict(n=n, t_f=t_f, T_c=T_c, t1=U(0.7, 1.1), dist=U(0.4, 1.0) * s if rng.random() < 0.5 else 0.0)
        D = plan["t1"] + (n - 1) * T_c + t_f + U(1.0, 1.8)
    elif action == "turn":
        plan = dict(angle=pick((-1, 1)) * pick((np.pi / 2, np.pi)), t0=U(0.4, 0.9))
        plan["dur"] = U(1.0, 1.6) * (1.0 if abs(plan["angle"]) < 2 else 1.4)
        D = plan["t0"] + plan["dur"] + U(0.8, 1.5)
    elif action == "wave":
        plan = dict(t0=U(0.3, 0.8), dur=U(1.5, 3.0), freq=U(1.5, 2.5), hand=pick(("left", "right", "both")))
        D = plan["t0"] + plan["dur"] + U(1.0, 1.8)
    elif action == "kick":
        plan = dict(n=int(rng.integers(1, 3)), t0=U(0.6, 1.0), dur=U(0.8, 1.1), gap=U(0.3, 0.7),
                    leg=pick(("left", "right")), high=rng.random() < 0.5)  # fmt: skip
        D = plan["t0"] + plan["n"] * (plan["dur"] + plan["gap"]) + U(0.6, 1.2)
    elif action in ("sit", "crouch"):
        up = rng.random() < (0.5 if action == "sit" else 0.8)
        plan = dict(t0=U(0.5, 1.0), down=U(1.0, 1.8), hold=U(0.8, 2.5), up=up)
        D = plan["t0"] + plan["down"] + plan["hold"] + (plan["down"] + U(0.5, 1.0) if plan["up"] else 0.0)
    elif action == "punch":
        plan = dict(n=int(rng.integers(2, 7)), t0=U(0.5, 0.9), every=U(0.45, 0.8), first=int(rng.integers(2)))
        D = plan["t0"] + plan["n"] * plan["every"] + U(0.8, 1.5)

    P, T = int(round(4.0 * fps)), max(int(round(D * fps)), 8)
    te = np.arange(-P, T + P) / fps
    frames = slice(P, P + T)
    t = te[frames]
    vel, yaw_rate, activity = np.zeros((len(te), 2)), np.zeros(len(te)), np.zeros(len(te))
    height, shift = np.full(T, h0 - st.crouch * s), np.zeros((T, 2))  # shift: body-frame x, z
    pelvis, spine, head = np.zeros((T, 3)), np.zeros((T, 3)), np.zeros((T, 2))
    spine[:, 1], head[:, 1] = st.lean, st.head - st.lean
    arms = np.tile(np.asarray(HANG), (T, 2, 1))  # (T, 2, 4)
    gait = Gait(1.0, 0.62, (0.0, 0.5), 0.09 * s * st.lift, (0.45, 0.45))
    phase = None
    tip_offset, extra_pitch = np.zeros((T, 2, 3)), np.zeros((T, 2))
    lifted = np.zeros((T, 2), dtype=bool)  # feet taken off the floor by the action itself
    poles = np.tile(np.asarray([leg.pole for leg in HUMAN_LEGS]), (T, 1, 1))  # knees forward
    suffix = ("",)

    if action in ("walk", "run"):
        run = action == "run"
        speed = pick(("slow", "normal") if style in ("tired", "sneaky") else ("slow", "normal", "fast"))
        lo, hi = {"slow": (0.6, 0.9), "normal": (1.0, 1.4), "fast": (1.5, 1.9)}[speed] if not run else (
            {"slow": (2.2, 2.7), "normal": (2.8, 3.4), "fast": (3.5, 4.2)}[speed])  # fmt: skip
        v = U(lo, hi) * s * st.speed
        direction = pick(("forward",) * 3 + ("circle",) if run else
                         ("forward",) * 4 + ("backward", "left", "right", "circle"))  # fmt: skip
        start, stop = rng.random() < 0.4, rng.random() < 0.4
        activity[:] = (_ss((te - 0.2) / 0.8) if start else 1.0) * (_ss((D - 0.4 - te) / 0.8) if stop else 1.0)
        if run:
            f = U(1.3, 1.5) * st.cadence
            gait = Gait(f, U(0.32, 0.38), (0.0, 0.5), U(0.15, 0.22) * s * st.lift, (0.6, 0.6))
        else:
            f = (0.55 + 0.27 * v / s) * st.cadence
            roll = 0.45 if direction in ("forward", "circle") else 0.1
            f *= 0.85 if direction in ("left", "right") else 1.0
            gait = Gait(f, 0.62, (0.0, 0.5), gait.lift, (roll, roll))
        if direction in ("left", "right"):  # short side steps, so that the feet never cross
            v = min(v, 0.28 * s * gait.freq / 0.45)
        side = pick(("left", "right"))
        heading_dir = {"forward": (0, 1), "circle": (0, 1), "backward": (0, -0.6), "left": (0.45, 0),
                       "right": (-0.45, 0)}  # fmt: skip
        vel[:] = np.asarray(heading_dir[direction]) * v * activity[:, None]
        if direction == "circle":
            radius = U(1.5, 3.0) * (2.0 if run else 1.0)
            yaw_rate[:] = (1 if side == "left" else -1) * v / radius * activity
            pelvis[:, 2] = -np.arctan(v * yaw_rate[frames] / GRAVITY)  # lean into the curve
            labels["side"] = side
        a, cyc = activity[frames], 2 * np.pi * gait.freq * t
        if run:  # lowest at mid-stance, highest in flight
            height += a * 0.05 * s * -np.cos(2 * cyc - 2 * np.pi * gait.duty)
            arms[:, :, 3] = 1.4
            swing, spine[:, 1] = 0.55 * st.swing, spine[:, 1] + 0.12 * a
        else:  # highest at each mid-stance
            height += a * st.bounce * s * np.cos(2 * cyc - 2 * np.pi * gait.duty)
            swing = 0.3 * st.swing * (0.4 if direction in ("left", "right") else 1.0)
        shift[:, 0] = a * 0.02 * s * np.cos(cyc - np.pi * gait.duty)  # over the stance foot
        pelvis[:, 0] = -0.08 * a * np.cos(cyc)  # the swing leg's hip comes forward
        spine[:, 0] = 1.5 * 0.08 * a * np.cos(cyc)  # shoulders counter-rotate
        arms[:, 0, 0] += -swing * a * np.cos(cyc)  # each arm swings with the opposite leg
        arms[:, 1, 0] += swing * a * np.cos(cyc)
        arms[:, :, 3] += 0.3 * np.clip(arms[:, :, 0], 0, None)
        speed_mps = round(float(v * np.hypot(*heading_dir[direction])), 2)
        labels.update(speed=speed, direction=direction, speed_mps=speed_mps)
        verb = ("jogs" if speed == "slow" else "runs") if run else "walks"
        moves = {
            "forward": ("runs forward", "runs straight ahead", "is running forward") if run else (
                "walks forward", "walks straight ahead", "strolls forward", "is walking forward"),
            "backward": ("walks backwards", "walks backward", "steps backwards", "moves backward"),
            "left": ("walks sideways to the left", "side-steps to the left", "shuffles to the left"),
            "right": ("walks sideways to the right", "side-steps to the right", "shuffles to the right"),
            "circle": (f"{verb} in a circle", f"{verb} in a circle to the {side}",
                       f"{verb} around in a {'counterclockwise' if side == 'left' else 'clockwise'} circle"),
        }[direction]  # fmt: skip
        if run and speed != "normal" and direction == "forward":
            moves += ("jogs forward", "jogs ahead") if speed == "slow" else ("sprints forward", "dashes ahead")
        speed_words = SPEED_WORDS[speed] if not run else {
            "slow": ("at an easy pace", "lightly", ""), "normal": ("",), "fast": ("at full speed", "very fast"),
        }[speed]  # fmt: skip
        groups = [speed_words, STYLE_WORDS[style]]
        suffix = ("and then stops", "before coming to a stop") if stop else ("",)
        if start:
            groups.append(("from a standstill", "after standing still"))
    elif action == "jump":
        takeoffs = [plan["t1"] + k * plan["T_c"] for k in range(plan["n"])]
        duty = 1 - plan["t_f"] / plan["T_c"]
        phase = np.repeat(_jump_phase(te, takeoffs, plan["t_f"], duty)[:, None], 2, 1)
        gait = Gait(1.0, duty, (0.0, 0.0), 0.5 * GRAVITY * plan["t_f"] ** 2 / 8, (0.5, 0.5))
        activity[:] = 1.0
        dy, vz = _jump_root(te, takeoffs, plan["t_f"], U(0.12, 0.2) * s, plan["dist"], 1.0)
        height += dy[frames]
        vel[:, 1] = vz
        crouch = np.clip(-dy[frames], 0, None) / (0.2 * s)
        spine[:, 1] += 0.5 * crouch
        pelvis[:, 1] = 0.3 * crouch
        swing = sum(-0.7 * _bump(t, to - 0.2, 0.2) + 2.2 * _bump(t, to + 0.12, 0.3) for to in takeoffs)
        arms[:, :, 0] += swing[:, None]  # back in the crouch, up at take-off
        arms[:, :, 3] += 0.3 * crouch[:, None]
        forward = plan["dist"] > 0
        labels.update(direction="forward" if forward else "in_place", count=plan["n"])
        moves = ("jumps forward", "leaps forward", "does a long jump forward") if forward else (
            "jumps in place", "jumps up and down", "hops on the spot")  # fmt: skip
        groups = [{1: ("",), 2: ("twice",), 3: ("three times",)}[plan["n"]]]
    elif action == "turn":
        x = (te - plan["t0"]) / plan["dur"]
        yaw_rate[:] = plan["angle"] * np.where((x > 0) & (x < 1), 6 * x * (1 - x), 0.0) / plan["dur"]
        activity[:] = _window(te, plan["t0"] - 0.1, plan["t0"] + plan["dur"] + 0.2, 0.2)
        lead = 0 if plan["angle"] > 0 else 0.5  # step first with the foot on the turning side
        gait = Gait(1.1, 0.6, (lead, 0.5 - lead), 0.06 * s, (0.1, 0.1))
        heading_now = np.cumsum(yaw_rate) * (te[1] - te[0])
        head[:, 0] = 0.5 * (np.interp(t + 0.3, te, heading_now) - heading_now[frames])  # the head leads
        spine[:, 0] = head[:, 0]
        side = "left" if plan["angle"] > 0 else "right"
        labels.update(direction=side, angle=int(round(np.degrees(abs(plan["angle"])))))
        moves = (f"turns to the {side}", f"turns {side}", f"turns around to the {side}")
        if abs(plan["angle"]) > 2:
            moves = (f"turns around to the {side}", "turns around", "turns to face the other way")
        groups = [("", "in place", "on the spot")]
    elif action == "wave":
        w = _window(t, plan["t0"] + 0.5, plan["t0"] + plan["dur"] - 0.5, 0.5)
        wave = np.asarray((0.2, 1.75, np.pi / 2, 1.5))
        for i, hand in enumerate(("left", "right")):
            if plan["hand"] in (hand, "both"):
                arms[:, i] = arms[:, i] * (1 - w[:, None]) + wave * w[:, None]
                arms[:, i, 3] += w * 0.35 * np.sin(2 * np.pi * plan["freq"] * t + np.pi * i)
        spine[:, 2] = 0.06 * w * {"left": -1, "right": 1, "both": 0}[plan["hand"]]
        labels.update(hand=plan["hand"])
        hand = "both hands" if plan["hand"] == "both" else f"the {plan['hand']} hand"
        moves = (f"waves with {hand}", f"waves hello with {hand}", f"raises {hand} and waves")
        groups = [("", "while standing still")]
    elif action == "kick":
        i, k = (0, 1) if plan["leg"] == "left" else (1, 0)  # kicking and supporting leg
        reach, lift = (U(0.65, 0.75), U(0.7, 0.9)) if plan["high"] else (U(0.5, 0.6), U(0.3, 0.45))
        reach, lift = reach * s, lift * s
        for j in range(plan["n"]):
            t_k = plan["t0"] + j * (plan["dur"] + plan["gap"])
            x = (t - t_k) / plan["dur"]
            back, out = _bump(x, 0.22, 0.2), _bump(x, 0.55, 0.3)
            tip_offset[:, i, 1] += 0.12 * s * back + lift * out + 0.04 * s * np.sin(np.pi * np.clip(x, 0, 1))
            tip_offset[:, i, 2] += -0.25 * s * back + reach * out
            extra_pitch[:, i] += 0.6 * out
            poles[:, i, 1] += 2.0 * out  # the knee rises with the kick
            lifted[:, i] |= (x > 0) & (x < 1)
            spine[:, 1] -= 0.3 * out
        t_end = plan["t0"] + plan["n"] * (plan["dur"] + plan["gap"]) - plan["gap"]
        w = _window(t, plan["t0"], t_end, 0.35)
        shift[:, 0] = w * neutral[k, 0] * 0.7  # weight over the supporting foot
        arms[:, :, 1] += 0.5 * w[:, None]
        labels.update(leg=plan["leg"], height="high" if plan["high"] else "low", count=plan["n"])
        moves = (f"kicks with the {plan['leg']} leg", f"kicks forward with the {plan['leg']} foot",
                 f"does a {'high' if plan['high'] else 'low'} kick with the {plan['leg']} leg")  # fmt: skip
        groups = [("",) if plan["n"] == 1 else ("twice",)]
    elif action in ("sit", "crouch"):
        t1 = plan["t0"] + plan["down"] + plan["hold"]
        w = _ss((t - plan["t0"]) / plan["down"]) * (1 - _ss((t - t1) / plan["down"]) if plan["up"] else 1.0)
        moving = _bump(t, plan["t0"] + plan["down"] / 2, plan["down"] / 2) + (
            _bump(t, t1 + plan["down"] / 2, plan["down"] / 2) if plan["up"] else 0.0)  # fmt: skip
        if action == "sit":  # onto an invisible chair: hips back and down to knee height
            height += w * (0.52 * s - h0)
            shift[:, 1] = -0.3 * s * w
            spine[:, 1] += 0.5 * moving + 0.1 * w
            pelvis[:, 1] = 0.25 * moving
            arms[:, :, 0] += 0.6 * w[:, None]
            arms[:, :, 3] += 0.6 * w[:, None]
            moves = ("sits down", "takes a seat", "sits down on a chair")
            suffix = ("and then stands back up", "and gets up again") if plan["up"] else ("",)
        else:  # a squat: hips straight down, arms forward for balance
            height -= w * U(0.28, 0.4) * s
            shift[:, 1] = -0.12 * s * w
            spine[:, 1] += 0.3 * w + 0.2 * moving
            pelvis[:, 1] = 0.2 * w
            arms[:, :, 0] += 1.2 * w[:, None]
            moves = ("crouches down", "squats down", "bends the knees and squats")
            suffix = ("and stands back up", "and then rises again") if plan["up"] else ("",)
        head[:, 1] -= 0.5 * w * (spine[:, 1] + pelvis[:, 1])
        labels.update(stands_up=bool(plan["up"]))
        groups = [("", "slowly") if plan["down"] > 1.5 else ("",)]
    elif action == "punch":
        guard = _window(t, plan["t0"], plan["t0"] + plan["n"] * plan["every"], 0.4)
        arms[:] = arms * (1 - guard[:, None, None]) + np.asarray((0.5, 0.3, 0.0, 2.1)) * guard[:, None, None]
        for j in range(plan["n"]):
            i = (plan["first"] + j) % 2
            hit = _bump(t, plan["t0"] + (j + 0.5) * plan["every"], 0.18)
            arms[:, i] += hit[:, None] * (np.asarray((1.45, -0.45, 0.0, 0.1)) - arms[:, i])
            spine[:, 0] += (0.3 if i else -0.3) * hit  # the punching shoulder comes forward
        labels.update(count=plan["n"])
        moves = ("punches", "throws punches", "boxes", f"throws {plan['n']} punches", "punches the air")
        groups = [("", "with both fists", "alternating fists")]
    else:  # idle
        looks = rng.random() < 0.5
        shift[:, 0] = 0.02 * s * np.sin(2 * np.pi * U(0.15, 0.3) * t + U(0, 6.3))
        spine[:, 1] += 0.02 * np.sin(2 * np.pi * 0.25 * t)  # breathing
        if looks:
            head[:, 0] = 0.6 * np.sin(2 * np.pi * U(0.15, 0.3) * t) * _window(t, 0.5, D - 0.5, 0.5)
        labels.update(looks_around=bool(looks))
        moves = ("stands and looks around", "looks around while standing") if looks else (
            "stands still", "stands in place", "waits idly")  # fmt: skip
        groups = [STYLE_WORDS[style]]

    if phase is None:
        phase = gait.phase(te)
    path = _Path.integrate(te, P, vel, yaw_rate)
    tips, foot_yaw, pitch, contact = _feet(te, frames, phase, gait, activity, path, neutral)
    x, z, heading = path.at(t)
    dx, dz = _yaw_apply(foot_yaw, tip_offset[..., 0], tip_offset[..., 2])
    tips += np.stack((dx, tip_offset[..., 1], dz), -1)
    pitch, contact = pitch + extra_pitch, contact & ~lifted
    dx, dz = _yaw_apply(heading, shift[:, 0], shift[:, 1])
    root_xz = torch.as_tensor(np.stack((x + dx, z + dz), -1))
    rot = _human_rotations(off, heading, pelvis, spine, head, arms)
    foot_q = quat_mul(_rot("y", foot_yaw), _rot("x", pitch))
    rot, pos = _solve_legs(SMPL22, off, HUMAN_LEGS, rot, root_xz, height, torch.as_tensor(tips), foot_q,
                           torch.as_tensor(contact), torch.as_tensor(poles), max(1, round(0.12 * fps)))  # fmt: skip
    # contacts per skeleton.feet joint: the ankle (heel) while the foot is flat, the toe all stance
    flat = contact & (pitch < 1e-3)
    contacts = np.stack((flat[:, 0], contact[:, 0], flat[:, 1], contact[:, 1]), -1)
    texts = _captions(rng, PEOPLE, moves, *groups, suffixes=suffix)
    return _clip(SMPL22, "human", index, action, fps, rot, pos, off, texts, labels), contacts


# ----------------------------------------------------------------------------- quadrupeds


@dataclass(frozen=True)
class Animal:
    """Body proportions relative to the SMAL35 rest dog, and what the animal does."""

    size: float
    legs: float
    spine: float
    neck: float
    tail: float
    tail_pitch: float  # tail carriage, + up (rad)
    tail_curl: float = 0.0  # per tail segment (rad)
    width: float = 1.0
    flex: float = 0.2  # spine flexion in the gallop (rad)
    neck_pitch: float = 0.0  # head carriage, + lower (rad)
    wags: bool = False
    actions: tuple[str, ...] = ANIMAL_ACTIONS


_HOOVED = ("walk", "trot", "gallop", "jump", "lie", "idle", "turn")
ANIMALS = {
    "dog": Animal(1.0, 1.0, 1.0, 1.0, 1.0, 0.35, 0.08, wags=True),
    "cat": Animal(0.45, 0.9, 1.15, 0.8, 1.6, 0.9, 0.12, flex=0.35),
    "fox": Animal(0.62, 0.9, 1.1, 0.9, 1.5, -0.15, 0.03, flex=0.3, wags=True),
    "horse": Animal(2.4, 1.2, 1.0, 1.6, 1.1, -1.0, 0.05, width=1.15, flex=0.06, neck_pitch=0.35, actions=_HOOVED),
    "cow": Animal(2.0, 0.8, 1.35, 0.8, 1.1, -1.3, 0.02, width=1.35, flex=0.04, neck_pitch=0.6,
                  actions=("walk", "trot", "lie", "idle", "turn")),  # fmt: skip
    "deer": Animal(1.6, 1.3, 0.95, 1.4, 0.35, 0.4, width=0.9, flex=0.12, neck_pitch=0.1, actions=_HOOVED),
    "sheep": Animal(1.15, 0.75, 1.1, 0.8, 0.4, -0.7, width=1.2, flex=0.08, neck_pitch=0.4, actions=_HOOVED),
}
_LEG_BONES = [8, 9, 10, 12, 13, 14, 18, 19, 20, 22, 23, 24]
# footfall lags (LF, LH, RF, RH): lateral-sequence 4-beat walk, diagonal trot, bound-like gallop
WALK, TROT, GALLOP = (0.25, 0.0, 0.75, 0.5), (0.0, 0.5, 0.5, 0.0), (0.45, 0.0, 0.55, 0.1)


def _animal_offsets(spec: Animal, rng) -> tuple[np.ndarray, float]:
    """This individual's offsets: the category's proportions with a few percent of variation."""
    size = rng.uniform(0.9, 1.1)
    off = SMAL35.rest_offsets.astype(np.float64).copy()
    off[_LEG_BONES] *= spec.legs * rng.uniform(0.96, 1.04)
    off[1:7] *= spec.spine * rng.uniform(0.95, 1.05)
    off[[15, 16, 32, 33, 34]] *= spec.neck * rng.uniform(0.95, 1.05)
    off[25:32] *= spec.tail * rng.uniform(0.9, 1.1)
    off[[7, 11, 17, 21], 0] *= spec.width
    off *= spec.size * size
    off[0] = 0.0
    off[0, 1] = -_rest_rel(SMAL35, off)[[10, 14, 20, 24], 1].min()  # paws on the floor
    return off, size


def _animal_rotations(heading, pitch_up, spine_flex, spine_bend, neck, head_pitch, tail, wag, curl) -> torch.Tensor:
    """(T, 35, 4) body rotations (legs at rest). Angles (T,): pitch_up raises the nose, spine_flex
    (+ arches the back) and spine_bend (+ bends left) spread over the spine, neck (T, 2) yaw,
    pitch (+ lowers), tail (+ raises it in the world, whatever the body pitch), wag, curl."""
    rot = quat_identity((len(heading), 35), F64)
    rot[:, 0] = quat_mul(_rot("y", heading), _rot("x", -pitch_up + 0.5 * spine_flex))
    for j in range(1, 7):
        rot[:, j] = quat_mul(_rot("y", spine_bend / 6), _rot("x", -spine_flex / 6))
    rot[:, 15] = quat_mul(_rot("y", neck[:, 0]), _rot("x", neck[:, 1]))
    rot[:, 16] = _rot("x", head_pitch)
    rot[:, 25] = quat_mul(_rot("y", wag), _rot("x", tail + pitch_up - 0.5 * spine_flex))
    for i, j in enumerate(range(26, 31)):
        rot[:, j] = quat_mul(_rot("y", wag * (0.3 + 0.15 * i)), _rot("x", curl))
    return rot


def _animal(rng, index: int, fps: float) -> tuple[Clip, np.ndarray]:
    """Quadruped clip ``index``: category, then action, cycle with the index; the rest is sampled."""
    names = list(ANIMALS)
    category = names[index % len(names)]
    spec = ANIMALS[category]
    action = spec.actions[(index // len(names) + index % len(names)) % len(spec.actions)]  # staggered
    pick = lambda xs: xs[rng.integers(len(xs))]  # noqa: E731
    U = rng.uniform
    off, size = _animal_offsets(spec, rng)
    rest = _rest_rel(SMAL35, off)
    h = off[0, 1]  # hip height: sets speeds and timing by dynamic similarity
    ts, w0 = np.sqrt(h / 0.56), np.sqrt(GRAVITY / h)
    h0 = 0.97 * h
    neutral = rest[[10, 20, 14, 24]][:, [0, 2]]
    l_front = [np.linalg.norm(off[j]) for j in (8, 9, 10)]

    D, plan = {"idle": U(2, 8)}.get(action, 0.0), {}
    if action in ("walk", "trot", "gallop", "turn"):
        speed = pick(("slow", "normal", "fast")) if action != "turn" else "normal"
        k_f, k_s = {"slow": (0.85, 0.75), "normal": (1.0, 1.0), "fast": (1.1, 1.2)}[speed]
        f, stride, duty, offs, lift = {
            "walk": (0.3, 1.1, 0.68, WALK, 0.12), "turn": (0.3, 1.1, 0.68, WALK, 0.12),
            "trot": (0.5, 1.6, 0.45, TROT, 0.15), "gallop": (0.62, 2.6, 0.3, GALLOP, 0.2),
        }[action]  # fmt: skip
        f *= w0 * k_f * U(0.92, 1.08)
        v = f * stride * h * k_s
        D = {"walk": U(3, 10), "trot": U(3, 8), "gallop": U(2.5, 6)}.get(action, 0.0)
        if action == "turn":  # an arc of 1.5-2.5 body lengths (peak yaw rate v / radius), at most 8 s long
            radius = U(1.5, 2.5) * max(h, rest[7, 2] - rest[17, 2])
            angle = min(U(np.pi / 2, np.pi), 8.0 * v / (1.5 * radius))
            plan = dict(side=pick(("left", "right")), angle=angle, t0=U(0.4, 0.8), dur=1.5 * angle * radius / v)
            D = plan["t0"] + plan["dur"] + U(0.4, 0.8)
    elif action == "jump":
        plan = dict(t1=U(0.6, 1.2), t_f=U(0.35, 0.5) * ts, dist=U(1.2, 2.2) * h)
        D = plan["t1"] + plan["t_f"] + U(1.2, 2.0)
    elif action in ("sit", "lie"):
        plan = dict(t0=U(0.5, 1.0), down=U(1.2, 2.0) * ts)
        D = plan["t0"] + plan["down"] + U(1.0, 3.0)
    P, T = int(round(4.0 * fps)), max(int(round(D * fps)), 8)
    te = np.arange(-P, T + P) / fps
    frames = slice(P, P + T)
    t = te[frames]
    vel, yaw_rate, activity = np.zeros((len(te), 2)), np.zeros(len(te)), np.zeros(len(te))
    height, shift_z = np.full(T, h0), np.zeros(T)
    pitch_up, flex, bend, head_pitch = np.zeros(T), np.zeros(T), np.zeros(T), np.zeros(T)
    neck, wag = np.tile((0.0, spec.neck_pitch), (T, 1)), np.zeros(T)
    gait = Gait(0.3 * w0, 0.7, WALK, 0.12 * h, (0.5, 0.3, 0.5, 0.3))
    phase, labels = None, {"action": action}
    foot_pitch, slide = np.zeros((T, 4)), np.zeros((T, 4))  # extra paw pitch, forward paw slide (m)
    poles = np.tile(np.asarray([leg.pole for leg in ANIMAL_LEGS]), (T, 1, 1))
    lifted = np.zeros((T, 4), dtype=bool)
    groups = []
    # the tail hangs no lower than the floor allows
    tail_len = np.linalg.norm(off[25:32], axis=-1).sum()
    tail = np.full(T, max(spec.tail_pitch, -np.arcsin(min(1.0, 0.75 * h / tail_len))))

    if action in ("walk", "trot", "gallop", "turn"):
        gait = Gait(f, duty, offs, lift * h, (0.6, 0.3, 0.6, 0.3) if action != "gallop" else (1.0, 0.5, 1.0, 0.5))
        start = action != "gallop" and rng.random() < 0.3
        activity[:] = _ss((te - 0.2) / (0.8 * ts)) if start else 1.0
        vel[:, 1] = v * activity
        cyc = 2 * np.pi * f * t
        if action == "turn":
            side, x = plan["side"], (te - plan["t0"]) / plan["dur"]
            sign = 1 if side == "left" else -1
            yaw_rate[:] = sign * plan["angle"] * np.where((x > 0) & (x < 1), 6 * x * (1 - x), 0) / plan["dur"]
            bend[:] = 0.5 * np.interp(t, te, yaw_rate) * h / v  # the spine curves into the turn
            neck[:, 0] = 0.5 * bend
            labels.update(direction=side, angle=int(round(np.degrees(plan["angle"]))))
        if action == "gallop":  # one bob per stride; back arched in the gathered flight
            phase_c = cyc - 2 * np.pi * 0.93
            height += 0.05 * h * np.cos(phase_c)
            flex[:] = spec.flex * np.cos(phase_c)
            pitch_up[:] = 0.06 * np.sin(phase_c)
            head_pitch[:] = 0.1 * np.cos(phase_c)
            tail[:] = np.maximum(tail, -0.3) + 0.15 * np.cos(phase_c)
        else:  # two bobs per stride, lateral spine wave, nodding head
            height += (0.01 if action != "trot" else 0.025) * h * np.cos(2 * cyc)
            bend += 0.04 * np.cos(cyc)
            neck[:, 1] += 0.06 * np.cos(2 * cyc)
            wag[:] = 0.15 * np.sin(cyc)
        labels.update(speed=speed, speed_mps=round(float(v), 2))
        labels.setdefault("direction", "forward")
        moves = {
            "walk": ("walks forward", "walks ahead", "is walking forward", "strolls along"),
            "trot": ("trots forward", "trots along", "is trotting ahead", "moves forward at a trot"),
            "gallop": ("gallops forward", "runs forward at a gallop", "is galloping ahead", "runs fast"),
            "turn": (f"turns {plan.get('side')} while walking", f"walks in a curve to the {plan.get('side')}",
                     f"walks and turns {plan.get('side')}"),
        }[action]  # fmt: skip
        if action == "gallop" and category in ("dog", "cat", "fox"):
            moves += ("bounds forward", "dashes forward", "sprints ahead")
        groups = [SPEED_WORDS[speed] if action != "gallop" else ("", "at full speed", "quickly")]
        if start:
            groups.append(("from a standstill", "after standing still"))
    elif action == "jump":
        duty = 0.6
        takeoffs = [plan["t1"]]
        front = _jump_phase(te, takeoffs, plan["t_f"], duty)
        hind = np.interp(te - 0.08 * ts, te, front)  # the hind legs push off and land last
        phase = np.stack((front, hind, front, hind), -1)
        gait = Gait(1.0, duty, (0,) * 4, 0.4 * GRAVITY * plan["t_f"] ** 2 / 8, (1.0, 0.5, 1.0, 0.5))
        activity[:] = 1.0
        dy, vz = _jump_root(te, takeoffs, plan["t_f"], 0.15 * h, plan["dist"], ts)
        height += dy[frames]
        vel[:, 1] = vz
        to, la = plan["t1"], plan["t1"] + plan["t_f"]
        pitch_up[:] = 0.3 * _bump(t, to + 0.05 * ts, 0.25 * ts) - 0.25 * _bump(t, la + 0.05 * ts, 0.25 * ts)
        flex[:] = -spec.flex * _bump(t, to + 0.1 * ts, 0.2 * ts) + spec.flex * _bump(t, la, 0.2 * ts)
        tail += (np.maximum(tail, -0.3) - tail) * _bump(t, (to + la) / 2, 0.5 * ts)  # streams out in flight
        labels.update(direction="forward")
        moves = ("jumps forward", "leaps forward", "makes a big leap forward", "jumps over an obstacle")
    elif action in ("sit", "lie"):
        w = _ss((t - plan["t0"]) / plan["down"])
        anchor = rest[7] - rest[0]  # front shoulder from the pelvis
        if action == "sit":  # rump down and back, body pitched up until the front legs are nearly straight
            y_sit, back, p = 0.25 * h, 0.15 * h, np.linspace(0.0, 1.2, 121)
            a_y = y_sit + anchor[1] * np.cos(p) + anchor[2] * np.sin(p)
            a_z = -back - anchor[1] * np.sin(p) + anchor[2] * np.cos(p)
            gap = np.hypot(a_y - (rest[9, 1] + h), a_z - rest[9, 2])  # shoulder to planted wrist
            p = p[np.argmin(np.abs(gap - 0.96 * (l_front[0] + l_front[1])))]
            pitch_up[:], shift_z[:] = p * w, -back * w
            height += (y_sit - h0) * w
            foot_pitch[:, [1, 3]] = -1.3 * w[:, None]  # hind metatarsals flat on the floor
            head_pitch[:] = 0.6 * p * w
            poles[:, 1], poles[:, 3] = (0.6, 0.3, 1.0), (-0.6, 0.3, 1.0)  # stifles a little out
            moves = ("sits down", "sits down on its haunches", "lowers itself into a sitting position", "sits")
        else:  # sphinx pose: elbows on the floor under the shoulders, forearms forward
            height += (0.95 * l_front[0] + 0.04 * h - anchor[1] - h0) * w
            foot_pitch[:] = np.asarray((-1.4, -1.3, -1.4, -1.3)) * w[:, None]
            reach = l_front[1] + l_front[2] * np.cos(0.17) + rest[7, 2] - rest[10, 2]
            slide[:, [0, 2]] = (reach * w)[:, None]
            moving = (w > 0) & (w < 1)
            lifted[:, [0, 2]] = moving[:, None]
            poles[:, [0, 2]] = (0.0, -1.0, -1.0)
            poles[:, 1], poles[:, 3] = (1.0, 0.0, 0.5), (-1.0, 0.0, 0.5)  # hind knees splay out
            neck[:, 1] += 0.2 * w
            moves = ("lies down", "lies down on the ground", "lies down to rest", "gets down onto the ground")
        tail[:] = tail * (1 - w) - 0.05 * w
        groups = [("", "slowly") if plan["down"] > 1.6 * ts else ("",)]
    else:  # idle
        looks = rng.random() < 0.6
        if looks:
            neck[:, 0] = 0.5 * np.sin(2 * np.pi * U(0.15, 0.3) * t) * _window(t, 0.5, D - 0.5, 0.5)
        flex[:] = 0.02 * np.sin(2 * np.pi * 0.3 * t)  # breathing
        wags = spec.wags and rng.random() < 0.6
        if wags:
            wag[:] = 0.5 * np.sin(2 * np.pi * U(2.0, 3.0) * t)
            tail += 0.3
        labels.update(looks_around=bool(looks), wags_tail=bool(wags))
        moves = ("stands and looks around", "looks around") if looks else (
            "stands still", "stands in place", "stands idle")  # fmt: skip
        groups = [("while wagging its tail", "wagging its tail") if wags else ("",)]

    if phase is None:
        phase = gait.phase(te)
    path = _Path.integrate(te, P, vel, yaw_rate)
    tips, paw_yaw, pitch, contact = _feet(te, frames, phase, gait, activity, path, neutral)
    x, z, heading = path.at(t)
    dx, dz = _yaw_apply(paw_yaw, 0.0, slide)
    tips[..., 0] += dx
    tips[..., 2] += dz
    tips[..., 1] += 0.03 * h * np.sin(np.pi * np.clip(slide / np.maximum(slide.max(0), 1e-9), 0, 1))
    contact &= ~lifted
    dx, dz = _yaw_apply(heading, 0.0, shift_z)
    root_xz = torch.as_tensor(np.stack((x + dx, z + dz), -1))
    rot = _animal_rotations(heading, pitch_up, flex, bend, neck, head_pitch, tail, wag, np.full(T, spec.tail_curl))
    foot_q = quat_mul(_rot("y", paw_yaw), _rot("x", pitch + foot_pitch))
    rot, pos = _solve_legs(SMAL35, off, ANIMAL_LEGS, rot, root_xz, height, torch.as_tensor(tips), foot_q,
                           torch.as_tensor(contact), torch.as_tensor(poles), max(1, round(0.12 * fps)))  # fmt: skip
    adjective = "big " if size > 1.06 else "small " if size < 0.94 else ""
    who = (f"a {category}", f"the {category}", f"a {adjective}{category}")
    texts = _captions(rng, who, moves, *groups)
    labels["size"] = round(float(size), 3)
    return _clip(SMAL35, category, index, action, fps, rot, pos, off, texts, labels), contact


# ----------------------------------------------------------------------------- public API


def _clip(skel, category, index, action, fps, rot, pos, off, texts, labels) -> Clip:
    return Clip(
        id=f"synth_{category}_{index:05d}_{action}", skeleton=skel, fps=float(fps),
        positions=pos.numpy().astype(np.float32), rotations=rot.numpy().astype(np.float32),
        offsets=off.astype(np.float32), texts=texts, labels=labels, category=category, source="synth",
    )  # fmt: skip


_KINDS: dict[str, tuple[int, Callable]] = {"human": (0, _human), "animal": (1, _animal)}


def synth_clip(kind: str, index: int, seed: int = 0, fps: float = 30.0) -> tuple[Clip, np.ndarray]:
    """Clip ``index`` of a kind ("human" or "animal") and its foot contacts (T, len(skeleton.feet)) bool.

    Actions cycle with the index (animals: categories cycle fastest), so small sets cover them all;
    everything else is drawn from a generator seeded by (seed, kind, index).
    """
    if kind not in _KINDS:
        raise UsageError(f"synth kind must be 'human' or 'animal', got {kind!r}")
    code, make = _KINDS[kind]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the tensors here are small: worker threads only add synchronisation
    try:
        return make(np.random.default_rng([seed, code, index]), index, fps)
    finally:
        torch.set_num_threads(threads)


def synth_clips(num_human: int, num_animal: int, seed: int = 0, fps: float = 30.0) -> Iterator[Clip]:
    """``num_human`` smpl22 clips, then ``num_animal`` smal35 clips, deterministic by seed."""
    for kind, count in (("human", num_human), ("animal", num_animal)):
        for index in range(count):
            yield synth_clip(kind, index, seed, fps)[0]
