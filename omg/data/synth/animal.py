"""Quadrupeds on SMAL-35: a species table, and one function per action.

Every species is a scaled and re-proportioned SMAL rest dog. Timing and speeds follow dynamic
similarity: with hip height h, speeds scale with sqrt(g h) and times with sqrt(h / g), so one
set of gait numbers (in hip heights and natural frequencies) fits a cat and a horse alike. How
a species moves lives in its ``Animal`` entry (proportions, tail and head carriage, and its
``GaitHabits``), not in the action code, so a species can be given its own habits there.

``make_animal_clip`` samples the individual and hands an ``AnimalContext`` to the action; the
action plans its timing (which fixes the time grid), keys ``AnimalChannels`` and returns them
with its labels and caption words; the shared tail solves the legs and writes the captions.
Random draws happen in a fixed order, which the committed mini shards depend on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from omg.data.synth import captions
from omg.data.synth.captions import CaptionParts
from omg.data.synth.curves import bump, smoothstep, window
from omg.data.synth.gait import ANIMAL_LEGS, GRAVITY, Gait, foot_targets, jump_phase, jump_root, solve_legs
from omg.data.synth.rig import axis_rotation, make_clip, rest_positions, rotate_by_heading
from omg.data.synth.timeline import ActionContext, RootPath, Timeline
from omg.motion.base import Clip
from omg.rotations import quat_identity, quat_mul
from omg.skeleton import SMAL35

ANIMAL_ACTIONS = ("walk", "trot", "gallop", "jump", "sit", "lie", "idle", "turn")

# footfall lags (LF, LH, RF, RH) in strides: lateral-sequence 4-beat walk, diagonal trot, bound-like gallop
WALK, TROT, GALLOP = (0.25, 0.0, 0.75, 0.5), (0.0, 0.5, 0.5, 0.0), (0.45, 0.0, 0.55, 0.1)
PAW_FOLD = (0.6, 0.3, 0.6, 0.3)  # LF, LH, RF, RH paw fold at lift-off (rad): front paws flip further
PUSH_PAW_FOLD = (1.0, 0.5, 1.0, 0.5)  # a gallop's or a leap's hard push-off


# ----------------------------------------------------------------------------- species


@dataclass(frozen=True)
class GaitHabit:
    """How a species moves in one gait. Lengths are in hip heights, frequencies in units of the
    pendulum frequency sqrt(g / hip height), angles in radians."""

    stride_frequency: float  # strides per second, per sqrt(g / hip height)
    stride_length: float  # hip heights travelled per stride
    duty_factor: float  # fraction of a stride each paw is planted
    footfall_lags: tuple[float, float, float, float]  # LF, LH, RF, RH touchdown lag, in strides
    paw_lift: float  # swing apex of a paw, hip heights
    paw_fold: tuple[float, float, float, float]  # LF, LH, RF, RH paw fold at lift-off
    # body motion. Symmetric gaits bob twice a stride with a lateral spine wave; a bounding gait
    # bobs once, flexing the back (by ``Animal.flex``) and rocking the body
    bounding: bool
    body_bob: float  # vertical bob amplitude, hip heights
    head_nod: float  # neck pitch (twice a stride), or head pitch (once a stride) when bounding
    tail_swing: float  # side to side, or up and down when bounding
    spine_sway: float = 0.0  # lateral spine wave (symmetric gaits)
    body_rock: float = 0.0  # nose-up pitch swing (bounding)
    high_point: float = 0.0  # bounding: stride fraction where the body is highest, back arched (the gathered flight)
    tail_lift: float = 0.0  # tail carried this much higher (+) or lower than at rest while in this gait (rad)


@dataclass(frozen=True)
class GaitHabits:
    """A species' gaits. A walking turn walks."""

    walk: GaitHabit
    trot: GaitHabit
    gallop: GaitHabit

    def of(self, gait: str) -> GaitHabit:
        return getattr(self, gait)


QUADRUPED_GAITS = GaitHabits(
    walk=GaitHabit(
        stride_frequency=0.3, stride_length=1.1, duty_factor=0.68, footfall_lags=WALK, paw_lift=0.12,
        paw_fold=PAW_FOLD, bounding=False, body_bob=0.01, head_nod=0.06, tail_swing=0.15, spine_sway=0.04,
    ),
    trot=GaitHabit(
        stride_frequency=0.5, stride_length=1.6, duty_factor=0.45, footfall_lags=TROT, paw_lift=0.15,
        paw_fold=PAW_FOLD, bounding=False, body_bob=0.025, head_nod=0.06, tail_swing=0.15, spine_sway=0.04,
    ),
    gallop=GaitHabit(
        stride_frequency=0.62, stride_length=2.6, duty_factor=0.3, footfall_lags=GALLOP, paw_lift=0.2,
        paw_fold=PUSH_PAW_FOLD, bounding=True, body_bob=0.05, head_nod=0.1, tail_swing=0.15, body_rock=0.06,
        high_point=0.93,
    ),
)  # fmt: skip


@dataclass(frozen=True)
class Animal:
    """A species: body proportions relative to the SMAL35 rest dog, carriage, gaits and what it does.

    ``gaits`` are the species' own habits (``SPECIES_GAITS``), made from ``QUADRUPED_GAITS`` with
    ``habits(...)``, e.g. ``habits(trot={"duty_factor": 0.5})``.
    """

    size: float  # overall scale
    legs: float  # leg length factor
    spine: float  # back length factor
    neck: float  # neck and head factor
    tail: float  # tail length factor
    tail_pitch: float  # tail carriage, + up (rad)
    tail_curl: float = 0.0  # per tail segment (rad)
    width: float = 1.0  # shoulder and hip width factor
    flex: float = 0.2  # spine flexion in the gallop and the jump (rad)
    neck_pitch: float = 0.0  # head carriage, + lower (rad)
    wags: bool = False  # wags its tail when idle (sometimes)
    actions: tuple[str, ...] = ANIMAL_ACTIONS
    gaits: GaitHabits = QUADRUPED_GAITS
    flight_tail_pitch: float = -0.3  # in a gallop or a leap the tail streams out no lower than this (rad)
    stance_height: float = 0.97  # standing root height, in hip heights: legs not quite straight


def habits(walk: dict | None = None, trot: dict | None = None, gallop: dict | None = None) -> GaitHabits:
    """``QUADRUPED_GAITS`` with some fields of each gait replaced, e.g. ``habits(trot={"duty_factor": 0.5})``."""
    return GaitHabits(*(replace(QUADRUPED_GAITS.of(name), **(fields or {}))
                        for name, fields in (("walk", walk), ("trot", trot), ("gallop", gallop))))


# Each species' gait habits, in the dimensionless units of ``GaitHabit`` (so that a difference here is
# a habit, not a consequence of size: dynamic similarity already scales every species' speed and
# timing by its hip height). The directions follow what is known of each species' locomotion:
# - dog: the reference; trots readily, tail carried up and swinging, moderate head nod.
# - cat: a long, low-slung, high-duty walk (cats keep three paws down for most of a stride), a
#   smooth body with little bob or nod, the tail held high and nearly still; supple spine (gallop).
# - fox: an economical, long-striding trot with a level back and head, the brush streamed
#   out behind, little sway (the fox's "floating" trot).
# - horse: the head-and-neck nod of the walk (two nods per stride), a trot with a marked vertical
#   bounce and suspension (low duty factor), a rigid back, tail down and quiet, lifted in the gallop.
# - cow: a slow, deliberate walk with a high duty factor, a large head bob and a rolling body sway
#   from its wide barrel; rarely trots, and stiffly.
# - deer: high-stepping (large paw lift), short stance in the trot, a bounding gallop with a high
#   body bob; the tail flagged up when running.
# - sheep: short, quick strides (high stride frequency, short stride length) with a bobbing head;
#   the tail hangs.
SPECIES_GAITS = {
    "dog": QUADRUPED_GAITS,
    "cat": habits(
        walk={"stride_frequency": 0.26, "stride_length": 1.25, "duty_factor": 0.75, "body_bob": 0.004,
              "head_nod": 0.02, "tail_swing": 0.04, "spine_sway": 0.07, "tail_lift": 0.25},
        trot={"stride_frequency": 0.46, "duty_factor": 0.5, "body_bob": 0.012, "head_nod": 0.02, "tail_swing": 0.05,
              "spine_sway": 0.06, "tail_lift": 0.2},
        gallop={"body_bob": 0.07, "body_rock": 0.09, "head_nod": 0.05},
    ),
    "fox": habits(
        walk={"stride_frequency": 0.28, "stride_length": 1.2, "head_nod": 0.03, "tail_swing": 0.05, "spine_sway": 0.02},
        trot={"stride_frequency": 0.44, "stride_length": 2.0, "duty_factor": 0.4, "body_bob": 0.012, "head_nod": 0.02,
              "tail_swing": 0.04, "spine_sway": 0.015, "tail_lift": 0.15},
        gallop={"tail_swing": 0.08, "tail_lift": 0.2},
    ),
    "horse": habits(
        walk={"stride_frequency": 0.28, "duty_factor": 0.63, "body_bob": 0.012, "head_nod": 0.2, "tail_swing": 0.06,
              "spine_sway": 0.02, "paw_lift": 0.09},
        trot={"stride_frequency": 0.52, "stride_length": 1.7, "duty_factor": 0.38, "body_bob": 0.045, "head_nod": 0.02,
              "tail_swing": 0.04, "spine_sway": 0.01, "paw_lift": 0.18},
        gallop={"head_nod": 0.18, "body_rock": 0.04, "tail_lift": 0.35},
    ),
    "cow": habits(
        walk={"stride_frequency": 0.24, "stride_length": 0.95, "duty_factor": 0.75, "body_bob": 0.015, "head_nod": 0.16,
              "tail_swing": 0.1, "spine_sway": 0.09, "paw_lift": 0.08},
        trot={"stride_frequency": 0.42, "stride_length": 1.3, "duty_factor": 0.52, "body_bob": 0.03, "head_nod": 0.1,
              "tail_swing": 0.12, "spine_sway": 0.07, "paw_lift": 0.1},
    ),
    "deer": habits(
        walk={"stride_frequency": 0.3, "duty_factor": 0.62, "paw_lift": 0.2, "head_nod": 0.08, "tail_swing": 0.03,
              "spine_sway": 0.02},
        trot={"duty_factor": 0.38, "paw_lift": 0.26, "body_bob": 0.035, "head_nod": 0.04, "tail_swing": 0.03,
              "spine_sway": 0.02, "tail_lift": 0.4},
        gallop={"body_bob": 0.09, "body_rock": 0.08, "paw_lift": 0.3, "tail_lift": 0.8},
    ),
    "sheep": habits(
        walk={"stride_frequency": 0.36, "stride_length": 0.85, "duty_factor": 0.7, "body_bob": 0.012, "head_nod": 0.12,
              "tail_swing": 0.05, "spine_sway": 0.05},
        trot={"stride_frequency": 0.6, "stride_length": 1.3, "duty_factor": 0.48, "body_bob": 0.03, "head_nod": 0.1,
              "tail_swing": 0.05, "spine_sway": 0.04},
        gallop={"stride_frequency": 0.7, "stride_length": 2.2},
    ),
}  # fmt: skip

_HOOVED = ("walk", "trot", "gallop", "jump", "lie", "idle", "turn")
ANIMALS = {  # size, legs, spine, neck, tail, tail_pitch, tail_curl, then by name
    "dog": Animal(1.0, 1.0, 1.0, 1.0, 1.0, 0.35, 0.08, wags=True, gaits=SPECIES_GAITS["dog"]),
    "cat": Animal(0.45, 0.9, 1.15, 0.8, 1.6, 0.9, 0.12, flex=0.35, gaits=SPECIES_GAITS["cat"]),
    "fox": Animal(0.62, 0.9, 1.1, 0.9, 1.5, -0.15, 0.03, flex=0.3, wags=True, gaits=SPECIES_GAITS["fox"]),
    "horse": Animal(2.4, 1.2, 1.0, 1.6, 1.1, -1.0, 0.05, width=1.15, flex=0.06, neck_pitch=0.35, actions=_HOOVED,
                    gaits=SPECIES_GAITS["horse"]),
    "cow": Animal(
        2.0, 0.8, 1.35, 0.8, 1.1, -1.3, 0.02, width=1.35, flex=0.04, neck_pitch=0.6,
        actions=("walk", "trot", "lie", "idle", "turn"), gaits=SPECIES_GAITS["cow"],
    ),
    "deer": Animal(1.6, 1.3, 0.95, 1.4, 0.35, 0.4, width=0.9, flex=0.12, neck_pitch=0.1, actions=_HOOVED,
                   gaits=SPECIES_GAITS["deer"]),
    "sheep": Animal(1.15, 0.75, 1.1, 0.8, 0.4, -0.7, width=1.2, flex=0.08, neck_pitch=0.4, actions=_HOOVED,
                    gaits=SPECIES_GAITS["sheep"]),
}
# pace -> (stride frequency factor, stride length factor)
PACES = {"slow": (0.85, 0.75), "normal": (1.0, 1.0), "fast": (1.1, 1.2)}
_LEG_BONES = [8, 9, 10, 12, 13, 14, 18, 19, 20, 22, 23, 24]
_PAWS = [10, 20, 14, 24]  # LF, LH, RF, RH paw tips


# ----------------------------------------------------------------------------- the individual


@dataclass(frozen=True, eq=False)
class AnimalBody:
    """One animal's proportions, and the scales of time and speed they set."""

    offsets: np.ndarray  # (35, 3) bone offsets (m); row 0 is the standing root position
    size: float  # this individual against its species, 0.9-1.1
    rest: np.ndarray  # (35, 3) rest joint positions relative to the root

    @classmethod
    def sample(cls, species: Animal, rng: np.random.Generator) -> AnimalBody:
        """The species' proportions with a few percent of variation, paws on the floor at rest."""
        size = rng.uniform(0.9, 1.1)
        offsets = SMAL35.rest_offsets.astype(np.float64).copy()
        offsets[_LEG_BONES] *= species.legs * rng.uniform(0.96, 1.04)
        offsets[1:7] *= species.spine * rng.uniform(0.95, 1.05)
        offsets[[15, 16, 32, 33, 34]] *= species.neck * rng.uniform(0.95, 1.05)
        offsets[25:32] *= species.tail * rng.uniform(0.9, 1.1)
        offsets[[7, 11, 17, 21], 0] *= species.width
        offsets *= species.size * size
        offsets[0] = 0.0
        offsets[0, 1] = -rest_positions(SMAL35, offsets)[_PAWS, 1].min()  # paws on the floor
        return cls(offsets, size, rest_positions(SMAL35, offsets))

    @property
    def hip_height(self) -> float:
        """The root's rest height (m): sets speeds and timing by dynamic similarity."""
        return self.offsets[0, 1]

    @property
    def time_scale(self) -> float:
        """How much slower than the SMAL rest dog (hip height 0.56 m) this body moves: sqrt(h / 0.56)."""
        return np.sqrt(self.hip_height / 0.56)

    @property
    def natural_frequency(self) -> float:
        """sqrt(g / h) (1/s): the pendulum frequency of its legs."""
        return np.sqrt(GRAVITY / self.hip_height)

    @property
    def neutral_paws(self) -> np.ndarray:
        """(4, 2) body-frame x, z of the LF, LH, RF, RH paw tips when standing."""
        return self.rest[_PAWS][:, [0, 2]]

    @property
    def front_leg(self) -> list[float]:
        """Lengths (m) of the upper arm, forearm and front paw."""
        return [np.linalg.norm(self.offsets[joint]) for joint in (8, 9, 10)]

    @property
    def tail_length(self) -> float:
        return np.linalg.norm(self.offsets[25:32], axis=-1).sum()

    @property
    def body_length(self) -> float:
        """Shoulder to hip along the back (m)."""
        return self.rest[7, 2] - self.rest[17, 2]


@dataclass(frozen=True, eq=False)
class AnimalContext(ActionContext):
    """What an action gets: the random generator, frame rate, the species and the individual."""

    category: str
    species: Animal
    body: AnimalBody
    open_duration_s: float  # idle: its duration, drawn up front; 0 for the others


@dataclass(eq=False)
class AnimalChannels:
    """Everything an action keys. (N,) arrays live on the padded grid, (T,) on the clip's frames; angles in rad."""

    timeline: Timeline
    velocity: np.ndarray  # (N, 2) root velocity in the body frame (x left, z forward), m/s
    yaw_rate: np.ndarray  # (N,) rad/s
    activity: np.ndarray  # (N,) 0 standing .. 1 stepping: scales paw lift and fold
    height: np.ndarray  # (T,) wanted root height (m); the legs' reach may lower it
    shift_z: np.ndarray  # (T,) root moved back (-) or forward from the path (m)
    pitch_up: np.ndarray  # (T,) the whole body, + raises the nose
    spine_flex: np.ndarray  # (T,) + arches the back
    spine_bend: np.ndarray  # (T,) + bends left
    neck: np.ndarray  # (T, 2) yaw, pitch (+ lowers)
    head_pitch: np.ndarray  # (T,) + lowers
    tail: np.ndarray  # (T,) tail pitch in the world, + raises
    wag: np.ndarray  # (T,) tail yaw
    gait: Gait
    phase: np.ndarray | None  # (N, 4) footfall phase when not the gait's own (jumps)
    paw_pitch: np.ndarray  # (T, 4) paw pitch added to the fold (rad), e.g. hind metatarsals flat when sitting
    paw_slide: np.ndarray  # (T, 4) paw moved forward of its footprint (m)
    poles: np.ndarray  # (T, 4, 3) where elbows and stifles point, in the anchor parent's frame
    lifted: np.ndarray  # (T, 4) bool, paws taken off the floor by the action itself

    @classmethod
    def standing(cls, ctx: AnimalContext, timeline: Timeline) -> AnimalChannels:
        """Standing square in the species' carriage, paws planted."""
        species, body, frames, padded = ctx.species, ctx.body, timeline.num_frames, timeline.num_padded
        hip_height = body.hip_height
        # the tail hangs no lower than the floor allows
        lowest_tail = -np.arcsin(min(1.0, 0.75 * hip_height / body.tail_length))
        return cls(
            timeline=timeline,
            velocity=np.zeros((padded, 2)),
            yaw_rate=np.zeros(padded),
            activity=np.zeros(padded),
            height=np.full(frames, species.stance_height * hip_height),
            shift_z=np.zeros(frames),
            pitch_up=np.zeros(frames),
            spine_flex=np.zeros(frames),
            spine_bend=np.zeros(frames),
            neck=np.tile((0.0, species.neck_pitch), (frames, 1)),
            head_pitch=np.zeros(frames),
            tail=np.full(frames, max(species.tail_pitch, lowest_tail)),
            wag=np.zeros(frames),
            # a slow walk's footfalls: with no activity and no travel the paws stay planted
            gait=Gait(0.3 * body.natural_frequency, 0.7, WALK, 0.12 * hip_height, (0.5, 0.3, 0.5, 0.3)),
            phase=None,
            paw_pitch=np.zeros((frames, 4)),
            paw_slide=np.zeros((frames, 4)),
            poles=np.tile(np.asarray([leg.pole for leg in ANIMAL_LEGS]), (frames, 1, 1)),
            lifted=np.zeros((frames, 4), dtype=bool),
        )


@dataclass(eq=False)
class AnimalMotion:
    """What an action returns: its keyed channels, its labels (after the action) and its words."""

    channels: AnimalChannels
    labels: dict
    caption: CaptionParts


# ----------------------------------------------------------------------------- travelling


@dataclass(frozen=True)
class _Stride:
    """A travelling gait's timing for this individual."""

    gait: str  # "walk", "trot" or "gallop"
    habit: GaitHabit
    pace: str  # "slow", "normal" or "fast"
    frequency_hz: float  # strides per second
    speed_mps: float


def _draw_stride(ctx: AnimalContext, gait: str, pace: str | None) -> _Stride:
    """Stride frequency and speed of ``gait`` at a pace (drawn when None), a few percent of jitter."""
    pace = ctx.pick(("slow", "normal", "fast")) if pace is None else pace
    frequency_factor, length_factor = PACES[pace]
    habit, body = ctx.species.gaits.of(gait), ctx.body
    frequency_hz = habit.stride_frequency * (body.natural_frequency * frequency_factor * ctx.uniform(0.92, 1.08))
    speed_mps = frequency_hz * habit.stride_length * body.hip_height * length_factor
    return _Stride(gait, habit, pace, frequency_hz, speed_mps)


def _draw_travel_durations(rng: np.random.Generator) -> dict[str, float]:
    """Durations (s) of walks, trots and gallops. All three are drawn for any travelling clip (a
    turn too, which ignores them), so that the draws after them line up with the mini shards."""
    return {"walk": rng.uniform(3, 10), "trot": rng.uniform(3, 8), "gallop": rng.uniform(2.5, 6)}


def _start_travel(ctx: AnimalContext, timeline: Timeline, stride: _Stride, may_start: bool):
    """Channels of an animal travelling forward at ``stride``, maybe from a standstill; and whether it started."""
    body, habit = ctx.body, stride.habit
    channels = AnimalChannels.standing(ctx, timeline)
    hip_height = body.hip_height
    channels.gait = Gait(stride.frequency_hz, habit.duty_factor, habit.footfall_lags, habit.paw_lift * hip_height,
                     habit.paw_fold)  # fmt: skip
    started = may_start and ctx.chance(0.3)
    channels.activity[:] = smoothstep((timeline.padded_seconds - 0.2) / (0.8 * body.time_scale)) if started else 1.0
    channels.velocity[:, 1] = stride.speed_mps * channels.activity
    return channels, started


def _sway(ctx: AnimalContext, channels: AnimalChannels, stride: _Stride) -> None:
    """Body motion phased with the strides (see ``GaitHabit``)."""
    habit, hip_height = stride.habit, ctx.body.hip_height
    cycle = 2 * np.pi * stride.frequency_hz * channels.timeline.seconds  # (T,) rad
    channels.tail += habit.tail_lift * channels.activity[channels.timeline.frames]  # the gait's tail carriage
    if habit.bounding:  # one bob per stride; back arched in the gathered flight
        from_high = cycle - 2 * np.pi * habit.high_point
        channels.height += habit.body_bob * hip_height * np.cos(from_high)
        channels.spine_flex[:] = ctx.species.flex * np.cos(from_high)
        channels.pitch_up[:] = habit.body_rock * np.sin(from_high)
        channels.head_pitch[:] = habit.head_nod * np.cos(from_high)
        streamed_tail = np.maximum(channels.tail, ctx.species.flight_tail_pitch)
        channels.tail[:] = streamed_tail + habit.tail_swing * np.cos(from_high)
    else:  # two bobs per stride, lateral spine wave, nodding head
        channels.height += habit.body_bob * hip_height * np.cos(2 * cycle)
        channels.spine_bend += habit.spine_sway * np.cos(cycle)
        channels.neck[:, 1] += habit.head_nod * np.cos(2 * cycle)
        channels.wag[:] = habit.tail_swing * np.sin(cycle)


def _travel(ctx: AnimalContext, gait: str) -> AnimalMotion:
    """Straight ahead in ``gait`` at a drawn pace; walks and trots sometimes start from a standstill."""
    stride = _draw_stride(ctx, gait, pace=None)
    duration_s = _draw_travel_durations(ctx.rng)[gait]
    channels, started = _start_travel(ctx, ctx.timeline(duration_s), stride, may_start=gait != "gallop")
    _sway(ctx, channels, stride)
    labels = {"speed": stride.pace, "speed_mps": round(float(stride.speed_mps), 2), "direction": "forward"}
    words = captions.animal_travel(action=gait, category=ctx.category, pace=stride.pace, side=None, started=started)
    return AnimalMotion(channels, labels, words)


def walk(ctx: AnimalContext) -> AnimalMotion:
    return _travel(ctx, "walk")


def trot(ctx: AnimalContext) -> AnimalMotion:
    return _travel(ctx, "trot")


def gallop(ctx: AnimalContext) -> AnimalMotion:
    return _travel(ctx, "gallop")


def turn(ctx: AnimalContext) -> AnimalMotion:
    """A walking arc of 90-180 degrees, 1.5-2.5 body lengths in radius, at most 8 s long."""
    body = ctx.body
    stride = _draw_stride(ctx, "walk", pace="normal")
    _draw_travel_durations(ctx.rng)  # unused: a turn lasts as long as its arc
    speed = stride.speed_mps
    radius_m = ctx.uniform(1.5, 2.5) * max(body.hip_height, body.body_length)
    angle = min(ctx.uniform(np.pi / 2, np.pi), 8.0 * speed / (1.5 * radius_m))  # rad; peak yaw rate is speed / radius
    side, start_s = ctx.pick(("left", "right")), ctx.uniform(0.4, 0.8)
    turn_s = 1.5 * angle * radius_m / speed
    timeline = ctx.timeline(start_s + turn_s + ctx.uniform(0.4, 0.8))

    channels, started = _start_travel(ctx, timeline, stride, may_start=True)
    progress = (timeline.padded_seconds - start_s) / turn_s
    sign = 1 if side == "left" else -1
    yaw_profile = np.where((progress > 0) & (progress < 1), 6 * progress * (1 - progress), 0)  # integrates to 1
    channels.yaw_rate[:] = sign * angle * yaw_profile / turn_s
    yaw_rate = np.interp(timeline.seconds, timeline.padded_seconds, channels.yaw_rate)  # (T,)
    channels.spine_bend[:] = 0.5 * yaw_rate * body.hip_height / speed
    channels.neck[:, 0] = 0.5 * channels.spine_bend  # the spine curves into the turn, the head leads it
    _sway(ctx, channels, stride)
    angle_deg = int(np.rint(np.degrees(angle)))
    labels = {"direction": side, "angle": angle_deg, "speed": stride.pace, "speed_mps": round(float(speed), 2)}
    words = captions.animal_travel(action="turn", category=ctx.category, pace=stride.pace, side=side, started=started)
    return AnimalMotion(channels, labels, words)


# ----------------------------------------------------------------------------- in place


def jump(ctx: AnimalContext) -> AnimalMotion:
    """One leap forward: crouch, push off with the hind legs last, fly with the back stretched, land."""
    body, species = ctx.body, ctx.species
    hip_height, time_scale = body.hip_height, body.time_scale
    takeoff_s, flight_s = ctx.uniform(0.6, 1.2), ctx.uniform(0.35, 0.5) * time_scale
    distance_m = ctx.uniform(1.2, 2.2) * hip_height
    timeline = ctx.timeline(takeoff_s + flight_s + ctx.uniform(1.2, 2.0))

    channels = AnimalChannels.standing(ctx, timeline)
    padded_seconds, seconds, frames = timeline.padded_seconds, timeline.seconds, timeline.frames
    duty = 0.6
    takeoffs_s = [takeoff_s]
    front = jump_phase(padded_seconds, takeoffs_s, flight_s, duty)
    hind = np.interp(padded_seconds - 0.08 * time_scale, padded_seconds, front)  # the hind legs push off and land last
    channels.phase = np.stack((front, hind, front, hind), -1)
    # all four legs share the schedule; paws tuck to 40% of the root's ballistic apex
    channels.gait = Gait(1.0, duty, (0,) * 4, 0.4 * GRAVITY * flight_s**2 / 8, PUSH_PAW_FOLD)
    channels.activity[:] = 1.0
    crouch_m = 0.15 * hip_height
    height_offset, forward_speed = jump_root(padded_seconds, takeoffs_s, flight_s, crouch_m, distance_m, time_scale)
    channels.height += height_offset[frames]
    channels.velocity[:, 1] = forward_speed
    landing_s = takeoff_s + flight_s
    nose_up = 0.3 * bump(seconds, takeoff_s + 0.05 * time_scale, 0.25 * time_scale)  # rearing to push off
    nose_down = 0.25 * bump(seconds, landing_s + 0.05 * time_scale, 0.25 * time_scale)  # front paws land first
    channels.pitch_up[:] = nose_up - nose_down
    stretched = -species.flex * bump(seconds, takeoff_s + 0.1 * time_scale, 0.2 * time_scale)  # back hollow at take-off
    gathered = species.flex * bump(seconds, landing_s, 0.2 * time_scale)  # back arched on landing
    channels.spine_flex[:] = stretched + gathered
    streamed = np.maximum(channels.tail, species.flight_tail_pitch) - channels.tail
    channels.tail += streamed * bump(seconds, (takeoff_s + landing_s) / 2, 0.5 * time_scale)  # streams out in flight
    return AnimalMotion(channels, {"direction": "forward"}, captions.animal_jump())


def sit(ctx: AnimalContext) -> AnimalMotion:
    """Rump down and back, body pitched up until the front legs are nearly straight."""
    channels, lowered, slow = _lower(ctx)
    body, hip_height, rest = ctx.body, ctx.body.hip_height, ctx.body.rest
    shoulder = rest[7] - rest[0]  # front shoulder from the pelvis
    sit_height_m, back_m = 0.25 * hip_height, 0.15 * hip_height
    # the body pitch at which the shoulder is 96% of the front leg from the planted wrist
    pitches = np.linspace(0.0, 1.2, 121)
    shoulder_y = sit_height_m + shoulder[1] * np.cos(pitches) + shoulder[2] * np.sin(pitches)
    shoulder_z = -back_m - shoulder[1] * np.sin(pitches) + shoulder[2] * np.cos(pitches)
    gap = np.hypot(shoulder_y - (rest[9, 1] + hip_height), shoulder_z - rest[9, 2])  # shoulder to planted wrist
    front_leg = body.front_leg
    pitch = pitches[np.argmin(np.abs(gap - 0.96 * (front_leg[0] + front_leg[1])))]
    channels.pitch_up[:], channels.shift_z[:] = pitch * lowered, -back_m * lowered
    channels.height += (sit_height_m - ctx.species.stance_height * hip_height) * lowered
    channels.paw_pitch[:, [1, 3]] = -1.3 * lowered[:, None]  # hind metatarsals flat on the floor
    channels.head_pitch[:] = 0.6 * pitch * lowered
    channels.poles[:, 1], channels.poles[:, 3] = (0.6, 0.3, 1.0), (-0.6, 0.3, 1.0)  # stifles a little out
    _settle_tail(channels, lowered)
    return AnimalMotion(channels, {}, captions.animal_sit(slow=slow))


def lie(ctx: AnimalContext) -> AnimalMotion:
    """Sphinx pose: elbows on the floor under the shoulders, forearms forward, hind legs folded."""
    channels, lowered, slow = _lower(ctx)
    body, hip_height, rest = ctx.body, ctx.body.hip_height, ctx.body.rest
    shoulder = rest[7] - rest[0]  # front shoulder from the pelvis
    front_leg = body.front_leg
    standing_m = ctx.species.stance_height * hip_height
    channels.height += (0.95 * front_leg[0] + 0.04 * hip_height - shoulder[1] - standing_m) * lowered  # elbows down
    channels.paw_pitch[:] = np.asarray((-1.4, -1.3, -1.4, -1.3)) * lowered[:, None]
    forearm_reach = front_leg[1] + front_leg[2] * np.cos(0.17) + rest[7, 2] - rest[10, 2]
    channels.paw_slide[:, [0, 2]] = (forearm_reach * lowered)[:, None]
    moving = (lowered > 0) & (lowered < 1)
    channels.lifted[:, [0, 2]] = moving[:, None]  # front paws slide forward off the floor
    channels.poles[:, [0, 2]] = (0.0, -1.0, -1.0)
    channels.poles[:, 1], channels.poles[:, 3] = (1.0, 0.0, 0.5), (-1.0, 0.0, 0.5)  # hind knees splay out
    channels.neck[:, 1] += 0.2 * lowered
    _settle_tail(channels, lowered)
    return AnimalMotion(channels, {}, captions.animal_lie(slow=slow))


def _lower(ctx: AnimalContext):
    """Timing of getting down (sit or lie): standing channels, how far down (T,) 0..1, and whether slowly."""
    start_s, down_s = ctx.uniform(0.5, 1.0), ctx.uniform(1.2, 2.0) * ctx.body.time_scale
    timeline = ctx.timeline(start_s + down_s + ctx.uniform(1.0, 3.0))
    lowered = smoothstep((timeline.seconds - start_s) / down_s)
    return AnimalChannels.standing(ctx, timeline), lowered, down_s > 1.6 * ctx.body.time_scale


def _settle_tail(channels: AnimalChannels, lowered) -> None:
    channels.tail[:] = channels.tail * (1 - lowered) - 0.05 * lowered  # resting along the floor


def idle(ctx: AnimalContext) -> AnimalMotion:
    """Standing and breathing; often looking around, and wagging if the species does."""
    timeline = ctx.timeline(ctx.open_duration_s)
    channels = AnimalChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    looks_around = ctx.chance(0.6)
    if looks_around:
        look_hz, settled = ctx.uniform(0.15, 0.3), window(seconds, 0.5, timeline.duration_s - 0.5, 0.5)
        channels.neck[:, 0] = 0.5 * np.sin(2 * np.pi * look_hz * seconds) * settled
    channels.spine_flex[:] = 0.02 * np.sin(2 * np.pi * 0.3 * seconds)  # breathing
    wags = ctx.species.wags and ctx.chance(0.6)
    if wags:
        channels.wag[:] = 0.5 * np.sin(2 * np.pi * ctx.uniform(2.0, 3.0) * seconds)
        channels.tail += 0.3  # raised while wagging
    labels = {"looks_around": bool(looks_around), "wags_tail": bool(wags)}
    return AnimalMotion(channels, labels, captions.animal_idle(looks_around=looks_around, wags=wags))


ANIMAL_ACTION_FUNCTIONS: dict[str, Callable[[AnimalContext], AnimalMotion]] = {
    "walk": walk, "trot": trot, "gallop": gallop, "jump": jump, "sit": sit, "lie": lie, "idle": idle, "turn": turn,
}  # fmt: skip
assert tuple(ANIMAL_ACTION_FUNCTIONS) == ANIMAL_ACTIONS


# ----------------------------------------------------------------------------- channels -> clip


def _body_rotations(heading, channels: AnimalChannels, tail_curl) -> torch.Tensor:
    """(T, 35, 4) local rotations with the legs at rest, from the channels and the heading (T,) (rad).
    Pitch and flex spread over the spine; the tail's pitch is kept in the world, whatever the body pitch."""
    pitch_up, spine_flex, spine_bend, wag = channels.pitch_up, channels.spine_flex, channels.spine_bend, channels.wag
    rotations = quat_identity((len(heading), 35), torch.float64)
    rotations[:, 0] = quat_mul(axis_rotation("y", heading), axis_rotation("x", -pitch_up + 0.5 * spine_flex))
    for joint in range(1, 7):  # the six spine joints
        rotations[:, joint] = quat_mul(axis_rotation("y", spine_bend / 6), axis_rotation("x", -spine_flex / 6))
    rotations[:, 15] = quat_mul(axis_rotation("y", channels.neck[:, 0]), axis_rotation("x", channels.neck[:, 1]))
    rotations[:, 16] = axis_rotation("x", channels.head_pitch)
    tail_pitch = channels.tail + pitch_up - 0.5 * spine_flex  # undo the body's pitch: the tail's is in the world
    rotations[:, 25] = quat_mul(axis_rotation("y", wag), axis_rotation("x", tail_pitch))
    for segment, joint in enumerate(range(26, 31)):  # the wag grows towards the tip
        rotations[:, joint] = quat_mul(axis_rotation("y", wag * (0.3 + 0.15 * segment)), axis_rotation("x", tail_curl))
    return rotations


def make_animal_clip(rng: np.random.Generator, index: int, fps: float) -> tuple[Clip, np.ndarray]:
    """Quadruped clip ``index``: species, then action, cycle with the index (staggered, so that small
    sets cover every pair); the rest is sampled. Contacts (T, 4) per ``SMAL35.feet``."""
    names = list(ANIMALS)
    category = names[index % len(names)]
    species = ANIMALS[category]
    action = species.actions[(index // len(names) + index % len(names)) % len(species.actions)]
    body = AnimalBody.sample(species, rng)
    open_duration_s = {"idle": rng.uniform(2, 8)}.get(action, 0.0)  # drawn for every clip
    ctx = AnimalContext(rng, fps, category, species, body, open_duration_s)
    motion = ANIMAL_ACTION_FUNCTIONS[action](ctx)
    channels, timeline = motion.channels, motion.channels.timeline
    hip_height, num_frames = body.hip_height, timeline.num_frames

    # root path and footfalls
    padded_seconds, frames = timeline.padded_seconds, timeline.frames
    phase = channels.phase if channels.phase is not None else channels.gait.phase(padded_seconds)
    path = RootPath.integrate(padded_seconds, timeline.pad_frames, channels.velocity, channels.yaw_rate)
    feet = foot_targets(padded_seconds, frames, phase, channels.gait, channels.activity, path, body.neutral_paws)
    x, z, heading = path.at(timeline.seconds)
    tips, slide = feet.tips, channels.paw_slide
    dx, dz = rotate_by_heading(feet.yaw, 0.0, slide)
    tips[..., 0] += dx
    tips[..., 2] += dz
    # a sliding paw lifts a little on its way
    tips[..., 1] += 0.03 * hip_height * np.sin(np.pi * np.clip(slide / np.maximum(slide.max(0), 1e-9), 0, 1))
    contact = feet.contact & ~channels.lifted
    dx, dz = rotate_by_heading(heading, 0.0, channels.shift_z)
    root_xz = torch.as_tensor(np.stack((x + dx, z + dz), -1))

    # body, then legs
    rotations = _body_rotations(heading, channels, np.full(num_frames, species.tail_curl))
    paw_rotations = quat_mul(axis_rotation("y", feet.yaw), axis_rotation("x", feet.pitch + channels.paw_pitch))
    rotations, positions = solve_legs(
        SMAL35, body.offsets, ANIMAL_LEGS, rotations, root_xz, channels.height, torch.as_tensor(tips), paw_rotations,
        torch.as_tensor(contact), torch.as_tensor(channels.poles), max(1, round(0.12 * fps)),
    )  # fmt: skip
    texts = captions.sample_captions(rng, captions.animal_subjects(category, body.size), motion.caption)
    labels = {"action": action, **motion.labels, "size": round(float(body.size), 3)}
    return make_clip(SMAL35, category, index, action, fps, rotations, positions, body.offsets, texts, labels), contact
