"""People on SMPL-22: one function per action, keyed the way an animator would.

``make_human_clip`` samples the individual and a mood, then hands a ``HumanContext`` to the
action. Each action first plans its timing (which fixes the clip's duration and so its time
grid), then keys its channels on a ``HumanChannels`` that starts from a neutral stance, and
returns them with its labels and caption words. The shared tail turns channels into a clip:
root path, footfalls, two-bone leg IK, foot contacts and captions.

Random draws happen in a fixed order (the committed mini shards depend on it): the
individual's proportions, the open-ended durations, the mood, the action's timing, the
action's own choices, then the captions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from omg.data.synth import captions
from omg.data.synth.captions import CaptionParts
from omg.data.synth.curves import bump, smoothstep, window
from omg.data.synth.gait import GRAVITY, HUMAN_LEGS, Gait, foot_targets, jump_phase, jump_root, solve_legs
from omg.data.synth.rig import axis_rotation, compose, make_clip, rest_positions, rotate_by_heading
from omg.data.synth.timeline import ActionContext, RootPath, Timeline
from omg.motion.base import Clip
from omg.rotations import quat_between, quat_conjugate, quat_identity, quat_mul
from omg.skeleton import SMPL22

HUMAN_ACTIONS = ("walk", "run", "jump", "turn", "wave", "kick", "sit", "crouch", "punch", "idle")


# ----------------------------------------------------------------------------- moods


@dataclass(frozen=True)
class Style:
    """How a mood changes locomotion and posture."""

    speed: float = 1.0  # walking / running speed factor
    cadence: float = 1.0  # step frequency factor
    bounce: float = 0.015  # vertical bob while walking (m, per unit body scale)
    lean: float = 0.05  # forward trunk lean (rad)
    lift: float = 1.0  # foot lift factor
    swing: float = 1.0  # arm swing factor
    crouch: float = 0.0  # pelvis lowered (m, per unit body scale)
    head: float = 0.0  # head pitch, + looks down (rad)


STYLES = {
    "neutral": Style(),
    "happy": Style(speed=1.1, cadence=1.15, bounce=0.045, lean=0.0, lift=1.3, swing=1.6, head=-0.1),
    "tired": Style(speed=0.7, cadence=0.85, bounce=0.008, lean=0.3, lift=0.6, swing=0.4, crouch=0.03, head=0.35),
    "sneaky": Style(speed=0.6, cadence=0.8, bounce=0.005, lean=0.35, lift=0.8, swing=0.4, crouch=0.12, head=-0.2),
    "proud": Style(speed=1.0, cadence=0.95, bounce=0.02, lean=-0.08, lift=1.1, swing=1.3, head=-0.12),
    "striding": Style(speed=1.15, cadence=0.85, bounce=0.02, lift=1.2, swing=1.3),  # long steps
}
# the moods an action may show besides neutral (which is drawn 3 times as often as any single one)
MOODS = {"walk": tuple(STYLES)[1:], "run": ("happy", "tired"), "idle": ("tired", "proud")}
NEUTRAL_WEIGHT = 3

# arm channels (flexion, abduction, twist, elbow) in rad, hanging relaxed at the sides
ARM_HANG = (0.05, 0.15, 0.0, 0.2)
# walking and running speeds (m/s per unit body scale) of each pace
WALK_SPEEDS = {"slow": (0.6, 0.9), "normal": (1.0, 1.4), "fast": (1.5, 1.9)}
RUN_SPEEDS = {"slow": (2.2, 2.7), "normal": (2.8, 3.4), "fast": (3.5, 4.2)}
# travel direction in the body frame (x left, z forward), relative to the drawn speed
DIRECTIONS = {"forward": (0, 1), "circle": (0, 1), "backward": (0, -0.6), "left": (0.45, 0), "right": (-0.45, 0)}


# ----------------------------------------------------------------------------- the individual


@dataclass(frozen=True, eq=False)
class HumanBody:
    """One person's proportions, and the stance they derive."""

    offsets: np.ndarray  # (22, 3) bone offsets (m); row 0 is the standing root position
    scale: float  # overall size, 0.9-1.1: lengths and speeds are multiplied by it
    rest: np.ndarray  # (22, 3) rest joint positions relative to the root
    standing_height: float  # root height standing with the knees barely bent (m)
    neutral_feet: np.ndarray  # (2, 2) body-frame x, z of the left and right foot tips when standing

    @classmethod
    def sample(cls, rng: np.random.Generator) -> HumanBody:
        """Overall 0.9-1.1 height with a little segment variation, soles on the floor at rest."""
        scale = rng.uniform(0.9, 1.1)
        offsets = SMPL22.rest_offsets.astype(np.float64) * scale
        offsets[[4, 5, 7, 8]] *= rng.uniform(0.96, 1.04)  # thighs and shins
        offsets[[18, 19, 20, 21]] *= rng.uniform(0.95, 1.05)  # arms
        offsets[[1, 2, 13, 14, 16, 17], 0] *= rng.uniform(0.92, 1.08)  # hip and shoulder width
        offsets[0] = 0.0
        offsets[0, 1] = -rest_positions(SMPL22, offsets)[:, 1].min()  # rest soles on the floor
        rest = rest_positions(SMPL22, offsets)
        neutral_feet = rest[[10, 11]][:, [0, 2]] * (0.85, 1.0)  # feet a little narrower than the hips
        return cls(offsets, scale, rest, 0.985 * offsets[0, 1], neutral_feet)


@dataclass(frozen=True, eq=False)
class HumanContext(ActionContext):
    """What an action gets: the random generator, frame rate, the person and the mood."""

    body: HumanBody
    style_name: str
    style: Style
    open_duration_s: float  # walk, run, idle: their duration, drawn up front; 0 for the others


@dataclass(eq=False)
class HumanChannels:
    """Everything an action keys. (N,) arrays live on the padded grid, (T,) on the clip's frames."""

    timeline: Timeline
    velocity: np.ndarray  # (N, 2) root velocity in the body frame (x left, z forward), m/s
    yaw_rate: np.ndarray  # (N,) rad/s
    activity: np.ndarray  # (N,) 0 standing .. 1 stepping: scales foot lift and heel-off
    height: np.ndarray  # (T,) wanted root height (m); the legs' reach may lower it
    shift: np.ndarray  # (T, 2) root offset from the path in the body frame (x, z), m
    pelvis: np.ndarray  # (T, 3) yaw, pitch (+ leans forward), roll (rad)
    spine: np.ndarray  # (T, 3) yaw, pitch, roll of the whole spine (rad), spread over three joints
    head: np.ndarray  # (T, 2) yaw, pitch of neck and head together (rad)
    arms: np.ndarray  # (T, 2, 4) left, right: flexion, abduction, twist, elbow (rad)
    gait: Gait
    phase: np.ndarray | None  # (N, 2) footfall phase when not the gait's own (jumps)
    tip_offset: np.ndarray  # (T, 2, 3) foot-tip offset from its footfall target, foot frame (m)
    extra_pitch: np.ndarray  # (T, 2) foot pitch added to the heel-off (rad)
    lifted: np.ndarray  # (T, 2) bool, feet taken off the floor by the action itself
    poles: np.ndarray  # (T, 2, 3) where the knees point, in the pelvis frame

    @classmethod
    def standing(cls, ctx: HumanContext, timeline: Timeline) -> HumanChannels:
        """A person standing still in their mood's posture, feet ready to walk in place."""
        body, style, frames, padded = ctx.body, ctx.style, timeline.num_frames, timeline.num_padded
        spine, head = np.zeros((frames, 3)), np.zeros((frames, 2))
        spine[:, 1], head[:, 1] = style.lean, style.head - style.lean  # the head looks ahead despite the lean
        return cls(
            timeline=timeline,
            velocity=np.zeros((padded, 2)),
            yaw_rate=np.zeros(padded),
            activity=np.zeros(padded),
            height=np.full(frames, body.standing_height - style.crouch * body.scale),
            shift=np.zeros((frames, 2)),
            pelvis=np.zeros((frames, 3)),
            spine=spine,
            head=head,
            arms=np.tile(np.asarray(ARM_HANG), (frames, 2, 1)),
            gait=Gait(1.0, 0.62, (0.0, 0.5), 0.09 * body.scale * style.lift, (0.45, 0.45)),
            phase=None,
            tip_offset=np.zeros((frames, 2, 3)),
            extra_pitch=np.zeros((frames, 2)),
            lifted=np.zeros((frames, 2), dtype=bool),
            poles=np.tile(np.asarray([leg.pole for leg in HUMAN_LEGS]), (frames, 1, 1)),  # knees forward
        )


@dataclass(eq=False)
class HumanMotion:
    """What an action returns: its keyed channels, its labels (after action and style) and its words."""

    channels: HumanChannels
    labels: dict
    caption: CaptionParts


# ----------------------------------------------------------------------------- locomotion


def walk(ctx: HumanContext) -> HumanMotion:
    return _locomote(ctx, running=False)


def run(ctx: HumanContext) -> HumanMotion:
    return _locomote(ctx, running=True)


def _locomote(ctx: HumanContext, running: bool) -> HumanMotion:
    """Walking (any direction, or a circle) or running (forward or a circle), maybe starting or stopping."""
    style, scale = ctx.style, ctx.body.scale
    timeline = ctx.timeline(ctx.open_duration_s)
    channels = HumanChannels.standing(ctx, timeline)
    padded_seconds, seconds, frames = timeline.padded_seconds, timeline.seconds, timeline.frames
    # what kind of walk: pace, direction, starting and stopping
    pace = ctx.pick(("slow", "normal") if ctx.style_name in ("tired", "sneaky") else ("slow", "normal", "fast"))
    speed_range = (RUN_SPEEDS if running else WALK_SPEEDS)[pace]
    speed = ctx.uniform(*speed_range) * scale * style.speed  # m/s
    direction = ctx.pick(("forward",) * 3 + ("circle",) if running else
                         ("forward",) * 4 + ("backward", "left", "right", "circle"))  # fmt: skip
    starts, stops = ctx.chance(0.4), ctx.chance(0.4)
    start_ramp = smoothstep((padded_seconds - 0.2) / 0.8) if starts else 1.0
    stop_ramp = smoothstep((timeline.duration_s - 0.4 - padded_seconds) / 0.8) if stops else 1.0
    channels.activity[:] = start_ramp * stop_ramp
    # footfalls: runs have a flight phase (duty < 0.5); cadence grows with walking speed
    if running:
        frequency = ctx.uniform(1.3, 1.5) * style.cadence
        duty, lift = ctx.uniform(0.32, 0.38), ctx.uniform(0.15, 0.22) * scale * style.lift
        channels.gait = Gait(frequency, duty, (0.0, 0.5), lift, (0.6, 0.6))
    else:
        frequency = (0.55 + 0.27 * speed / scale) * style.cadence
        roll = 0.45 if direction in ("forward", "circle") else 0.1  # little heel-off stepping sideways/back
        frequency *= 0.85 if direction in ("left", "right") else 1.0
        channels.gait = Gait(frequency, 0.62, (0.0, 0.5), channels.gait.lift_m, (roll, roll))
    if direction in ("left", "right"):  # short side steps, so that the feet never cross
        speed = min(speed, 0.28 * scale * channels.gait.frequency_hz / 0.45)
    side = ctx.pick(("left", "right"))
    channels.velocity[:] = np.asarray(DIRECTIONS[direction]) * speed * channels.activity[:, None]
    labels = {}
    if direction == "circle":
        radius_m = ctx.uniform(1.5, 3.0) * (2.0 if running else 1.0)
        channels.yaw_rate[:] = (1 if side == "left" else -1) * speed / radius_m * channels.activity
        channels.pelvis[:, 2] = -np.arctan(speed * channels.yaw_rate[frames] / GRAVITY)  # lean into the curve
        labels["side"] = side
    # body motion, phased with the footfalls
    activity, cycle = channels.activity[frames], 2 * np.pi * channels.gait.frequency_hz * seconds  # cycle: (T,) rad
    if running:  # lowest at mid-stance, highest in flight
        channels.height += activity * 0.05 * scale * -np.cos(2 * cycle - 2 * np.pi * channels.gait.duty_factor)
        channels.arms[:, :, 3] = 1.4  # elbows bent
        arm_swing = 0.55 * style.swing
        channels.spine[:, 1] = channels.spine[:, 1] + 0.12 * activity  # leaning into the run
    else:  # highest at each mid-stance
        channels.height += activity * style.bounce * scale * np.cos(2 * cycle - 2 * np.pi * channels.gait.duty_factor)
        arm_swing = 0.3 * style.swing * (0.4 if direction in ("left", "right") else 1.0)
    # the pelvis shifts over the stance foot
    channels.shift[:, 0] = activity * 0.02 * scale * np.cos(cycle - np.pi * channels.gait.duty_factor)
    channels.pelvis[:, 0] = -0.08 * activity * np.cos(cycle)  # the swing leg's hip comes forward
    channels.spine[:, 0] = 1.5 * 0.08 * activity * np.cos(cycle)  # shoulders counter-rotate
    channels.arms[:, 0, 0] += -arm_swing * activity * np.cos(cycle)  # each arm swings with the opposite leg
    channels.arms[:, 1, 0] += arm_swing * activity * np.cos(cycle)
    channels.arms[:, :, 3] += 0.3 * np.clip(channels.arms[:, :, 0], 0, None)  # elbows bend as the arm comes forward
    speed_mps = round(float(speed * np.hypot(*DIRECTIONS[direction])), 2)
    labels.update(speed=pace, direction=direction, speed_mps=speed_mps)
    words = captions.human_locomotion(
        run=running, direction=direction, side=side, speed=pace, style=ctx.style_name, started=starts, stops=stops
    )
    return HumanMotion(channels, labels, words)


# ----------------------------------------------------------------------------- in place


def jump(ctx: HumanContext) -> HumanMotion:
    """1-3 jumps, forward half the time: a crouch, a ballistic flight and a landing each."""
    scale = ctx.body.scale
    count, flight_s, period_s = int(ctx.rng.integers(1, 4)), ctx.uniform(0.3, 0.42), ctx.uniform(1.0, 1.3)
    first_takeoff_s = ctx.uniform(0.7, 1.1)
    distance_m = ctx.uniform(0.4, 1.0) * scale if ctx.chance(0.5) else 0.0
    timeline = ctx.timeline(first_takeoff_s + (count - 1) * period_s + flight_s + ctx.uniform(1.0, 1.8))

    channels = HumanChannels.standing(ctx, timeline)
    padded_seconds, seconds, frames = timeline.padded_seconds, timeline.seconds, timeline.frames
    takeoffs_s = [first_takeoff_s + k * period_s for k in range(count)]
    duty = 1 - flight_s / period_s
    channels.phase = np.repeat(jump_phase(padded_seconds, takeoffs_s, flight_s, duty)[:, None], 2, 1)  # both feet
    # both feet share the schedule; they tuck to half the root's ballistic apex
    channels.gait = Gait(1.0, duty, (0.0, 0.0), 0.5 * GRAVITY * flight_s**2 / 8, (0.5, 0.5))
    channels.activity[:] = 1.0
    crouch_m = ctx.uniform(0.12, 0.2) * scale
    height_offset, forward_speed = jump_root(padded_seconds, takeoffs_s, flight_s, crouch_m, distance_m, 1.0)
    channels.height += height_offset[frames]
    channels.velocity[:, 1] = forward_speed
    crouch = np.clip(-height_offset[frames], 0, None) / (0.2 * scale)  # (T,) ~0..1
    channels.spine[:, 1] += 0.5 * crouch
    channels.pelvis[:, 1] = 0.3 * crouch
    arm_swing = sum(
        -0.7 * bump(seconds, takeoff - 0.2, 0.2) + 2.2 * bump(seconds, takeoff + 0.12, 0.3) for takeoff in takeoffs_s
    )
    channels.arms[:, :, 0] += arm_swing[:, None]  # back in the crouch, up at take-off
    channels.arms[:, :, 3] += 0.3 * crouch[:, None]
    forward = distance_m > 0
    labels = {"direction": "forward" if forward else "in_place", "count": count}
    return HumanMotion(channels, labels, captions.human_jump(forward=forward, count=count))


def turn(ctx: HumanContext) -> HumanMotion:
    """A quarter or half turn on the spot, stepping round; the head leads."""
    angle = ctx.pick((-1, 1)) * ctx.pick((np.pi / 2, np.pi))  # rad, + turns left
    start_s = ctx.uniform(0.4, 0.9)
    turn_s = ctx.uniform(1.0, 1.6) * (1.0 if abs(angle) < 2 else 1.4)
    timeline = ctx.timeline(start_s + turn_s + ctx.uniform(0.8, 1.5))

    channels = HumanChannels.standing(ctx, timeline)
    padded_seconds, seconds, frames = timeline.padded_seconds, timeline.seconds, timeline.frames
    progress = (padded_seconds - start_s) / turn_s
    yaw_profile = np.where((progress > 0) & (progress < 1), 6 * progress * (1 - progress), 0.0)  # integrates to 1
    channels.yaw_rate[:] = angle * yaw_profile / turn_s
    channels.activity[:] = window(padded_seconds, start_s - 0.1, start_s + turn_s + 0.2, 0.2)
    lead = 0 if angle > 0 else 0.5  # step first with the foot on the turning side
    channels.gait = Gait(1.1, 0.6, (lead, 0.5 - lead), 0.06 * ctx.body.scale, (0.1, 0.1))
    heading = np.cumsum(channels.yaw_rate) * (padded_seconds[1] - padded_seconds[0])
    channels.head[:, 0] = 0.5 * (np.interp(seconds + 0.3, padded_seconds, heading) - heading[frames])  # looks ahead
    channels.spine[:, 0] = channels.head[:, 0]
    side = "left" if angle > 0 else "right"
    labels = {"direction": side, "angle": int(np.rint(np.degrees(abs(angle))))}
    return HumanMotion(channels, labels, captions.human_turn(side=side, turns_around=abs(angle) > 2))


def wave(ctx: HumanContext) -> HumanMotion:
    """One or both hands raised and waving, the trunk leaning away from the waving arm."""
    start_s, wave_s, wave_hz = ctx.uniform(0.3, 0.8), ctx.uniform(1.5, 3.0), ctx.uniform(1.5, 2.5)
    hand = ctx.pick(("left", "right", "both"))
    timeline = ctx.timeline(start_s + wave_s + ctx.uniform(1.0, 1.8))

    channels = HumanChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    raised = window(seconds, start_s + 0.5, start_s + wave_s - 0.5, 0.5)  # (T,) 0..1
    arm_up = np.asarray((0.2, 1.75, np.pi / 2, 1.5))  # flexion, abduction, twist, elbow
    for side, name in enumerate(("left", "right")):
        if hand in (name, "both"):
            channels.arms[:, side] = channels.arms[:, side] * (1 - raised[:, None]) + arm_up * raised[:, None]
            channels.arms[:, side, 3] += raised * 0.35 * np.sin(2 * np.pi * wave_hz * seconds + np.pi * side)
    channels.spine[:, 2] = 0.06 * raised * {"left": -1, "right": 1, "both": 0}[hand]
    return HumanMotion(channels, {"hand": hand}, captions.human_wave(hand=hand))


def kick(ctx: HumanContext) -> HumanMotion:
    """One or two kicks, high or low: wind back, strike, return, weight over the other foot."""
    count, start_s, kick_s = int(ctx.rng.integers(1, 3)), ctx.uniform(0.6, 1.0), ctx.uniform(0.8, 1.1)
    gap_s, leg, high = ctx.uniform(0.3, 0.7), ctx.pick(("left", "right")), ctx.chance(0.5)
    timeline = ctx.timeline(start_s + count * (kick_s + gap_s) + ctx.uniform(0.6, 1.2))

    body, scale, channels = ctx.body, ctx.body.scale, HumanChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    kicking, supporting = (0, 1) if leg == "left" else (1, 0)
    reach, lift = (ctx.uniform(0.65, 0.75), ctx.uniform(0.7, 0.9)) if high else (
        ctx.uniform(0.5, 0.6), ctx.uniform(0.3, 0.45))  # fmt: skip
    reach_m, lift_m = reach * scale, lift * scale
    for k in range(count):
        progress = (seconds - (start_s + k * (kick_s + gap_s))) / kick_s
        wind_back, strike = bump(progress, 0.22, 0.2), bump(progress, 0.55, 0.3)
        clearance = 0.04 * scale * np.sin(np.pi * np.clip(progress, 0, 1))
        channels.tip_offset[:, kicking, 1] += 0.12 * scale * wind_back + lift_m * strike + clearance
        channels.tip_offset[:, kicking, 2] += -0.25 * scale * wind_back + reach_m * strike
        channels.extra_pitch[:, kicking] += 0.6 * strike  # toes pointed
        channels.poles[:, kicking, 1] += 2.0 * strike  # the knee rises with the kick
        channels.lifted[:, kicking] |= (progress > 0) & (progress < 1)
        channels.spine[:, 1] -= 0.3 * strike  # leaning back
    end_s = start_s + count * (kick_s + gap_s) - gap_s
    kicking_time = window(seconds, start_s, end_s, 0.35)
    channels.shift[:, 0] = kicking_time * body.neutral_feet[supporting, 0] * 0.7  # weight over the supporting foot
    channels.arms[:, :, 1] += 0.5 * kicking_time[:, None]  # arms out for balance
    labels = {"leg": leg, "height": "high" if high else "low", "count": count}
    return HumanMotion(channels, labels, captions.human_kick(leg=leg, high=high, count=count))


def sit(ctx: HumanContext) -> HumanMotion:
    """Onto an invisible chair: hips back and down to knee height; maybe up again."""
    return _lower(ctx, sitting=True)


def crouch(ctx: HumanContext) -> HumanMotion:
    """A squat: hips straight down, arms forward for balance; usually up again."""
    return _lower(ctx, sitting=False)


def _lower(ctx: HumanContext, sitting: bool) -> HumanMotion:
    stands_up = ctx.chance(0.5 if sitting else 0.8)
    start_s, down_s, hold_s = ctx.uniform(0.5, 1.0), ctx.uniform(1.0, 1.8), ctx.uniform(0.8, 2.5)
    timeline = ctx.timeline(start_s + down_s + hold_s + (down_s + ctx.uniform(0.5, 1.0) if stands_up else 0.0))

    body, scale, channels = ctx.body, ctx.body.scale, HumanChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    rise_s = start_s + down_s + hold_s
    lowered = smoothstep((seconds - start_s) / down_s) * (
        1 - smoothstep((seconds - rise_s) / down_s) if stands_up else 1.0)  # fmt: skip
    moving = bump(seconds, start_s + down_s / 2, down_s / 2) + (
        bump(seconds, rise_s + down_s / 2, down_s / 2) if stands_up else 0.0)  # fmt: skip
    if sitting:
        channels.height += lowered * (0.52 * scale - body.standing_height)
        channels.shift[:, 1] = -0.3 * scale * lowered
        channels.spine[:, 1] += 0.5 * moving + 0.1 * lowered  # lean forward to get the weight over the feet
        channels.pelvis[:, 1] = 0.25 * moving
        channels.arms[:, :, 0] += 0.6 * lowered[:, None]  # hands towards the knees
        channels.arms[:, :, 3] += 0.6 * lowered[:, None]
        words = captions.human_sit(stands_up=stands_up, slow=down_s > 1.5)
    else:
        channels.height -= lowered * ctx.uniform(0.28, 0.4) * scale
        channels.shift[:, 1] = -0.12 * scale * lowered
        channels.spine[:, 1] += 0.3 * lowered + 0.2 * moving
        channels.pelvis[:, 1] = 0.2 * lowered
        channels.arms[:, :, 0] += 1.2 * lowered[:, None]
        words = captions.human_crouch(stands_up=stands_up, slow=down_s > 1.5)
    channels.head[:, 1] -= 0.5 * lowered * (channels.spine[:, 1] + channels.pelvis[:, 1])  # keep looking ahead
    return HumanMotion(channels, {"stands_up": bool(stands_up)}, words)


def punch(ctx: HumanContext) -> HumanMotion:
    """2-6 punches from a guard, alternating fists."""
    count, start_s, every_s = int(ctx.rng.integers(2, 7)), ctx.uniform(0.5, 0.9), ctx.uniform(0.45, 0.8)
    first_fist = int(ctx.rng.integers(2))  # 0 left, 1 right
    timeline = ctx.timeline(start_s + count * every_s + ctx.uniform(0.8, 1.5))

    channels = HumanChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    guard = window(seconds, start_s, start_s + count * every_s, 0.4)[:, None, None]  # (T, 1, 1)
    channels.arms[:] = channels.arms * (1 - guard) + np.asarray((0.5, 0.3, 0.0, 2.1)) * guard  # fists up
    for k in range(count):
        fist = (first_fist + k) % 2
        hit = bump(seconds, start_s + (k + 0.5) * every_s, 0.18)
        arm_out = np.asarray((1.45, -0.45, 0.0, 0.1))  # flexion, abduction, twist, elbow
        channels.arms[:, fist] += hit[:, None] * (arm_out - channels.arms[:, fist])
        channels.spine[:, 0] += (0.3 if fist else -0.3) * hit  # the punching shoulder comes forward
    return HumanMotion(channels, {"count": count}, captions.human_punch(count=count))


def idle(ctx: HumanContext) -> HumanMotion:
    """Standing, swaying a little and breathing; looking around half the time."""
    scale, timeline = ctx.body.scale, ctx.timeline(ctx.open_duration_s)
    channels = HumanChannels.standing(ctx, timeline)
    seconds = timeline.seconds
    looks_around = ctx.chance(0.5)
    sway_hz, sway_phase = ctx.uniform(0.15, 0.3), ctx.uniform(0, 6.3)
    channels.shift[:, 0] = 0.02 * scale * np.sin(2 * np.pi * sway_hz * seconds + sway_phase)  # weight shifts
    channels.spine[:, 1] += 0.02 * np.sin(2 * np.pi * 0.25 * seconds)  # breathing
    if looks_around:
        look_hz, settled = ctx.uniform(0.15, 0.3), window(seconds, 0.5, timeline.duration_s - 0.5, 0.5)
        channels.head[:, 0] = 0.6 * np.sin(2 * np.pi * look_hz * seconds) * settled
    labels = {"looks_around": bool(looks_around)}
    return HumanMotion(channels, labels, captions.human_idle(looks_around=looks_around, style=ctx.style_name))


HUMAN_ACTION_FUNCTIONS: dict[str, Callable[[HumanContext], HumanMotion]] = {
    "walk": walk, "run": run, "jump": jump, "turn": turn, "wave": wave,
    "kick": kick, "sit": sit, "crouch": crouch, "punch": punch, "idle": idle,
}  # fmt: skip
assert tuple(HUMAN_ACTION_FUNCTIONS) == HUMAN_ACTIONS


# ----------------------------------------------------------------------------- channels -> clip


def _draw_open_durations(rng: np.random.Generator) -> dict[str, float]:
    """Durations (s) of the open-ended actions. All three are drawn for every clip, whatever its
    action, so that the draws after them line up with the committed mini shards."""
    return {"walk": rng.uniform(3, 10), "run": rng.uniform(2.5, 7), "idle": rng.uniform(2, 8)}


def _body_rotations(offsets, heading, pelvis, spine, head, arms) -> torch.Tensor:
    """(T, 22, 4) local rotations with the legs at rest, from the channels (see ``HumanChannels``)
    and the heading (T,) (rad)."""
    rotations = quat_identity((len(heading), 22), torch.float64)
    rotations[:, 0] = compose(
        axis_rotation("y", heading + pelvis[:, 0]), axis_rotation("x", pelvis[:, 1]), axis_rotation("z", pelvis[:, 2])
    )
    for joint in (3, 6, 9):  # spine1-3 share the spine's bend
        rotations[:, joint] = compose(
            axis_rotation("y", spine[:, 0] / 3),
            axis_rotation("x", spine[:, 1] / 3),
            axis_rotation("z", spine[:, 2] / 3),
        )
    for joint in (12, 15):  # neck and head share the head's turn
        rotations[:, joint] = compose(axis_rotation("y", head[:, 0] / 2), axis_rotation("x", head[:, 1] / 2))
    down = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    for side, (shoulder, elbow, wrist) in enumerate(((16, 18, 20), (17, 19, 21))):
        mirror, (flexion, abduction, twist, elbow_bend) = 1 - 2 * side, arms[:, side].T
        # the arm is posed from hanging straight down; the rest T-pose is rotated there first
        hang_upper = quat_between(torch.as_tensor(offsets[elbow]), down)
        hang_fore = quat_between(torch.as_tensor(offsets[wrist]), down)
        rotations[:, shoulder] = compose(
            axis_rotation("x", -flexion),
            axis_rotation("z", mirror * abduction),
            axis_rotation("y", mirror * twist),
            hang_upper,
        )
        rotations[:, elbow] = compose(quat_conjugate(hang_upper), axis_rotation("x", -elbow_bend), hang_fore)
    return rotations


def make_human_clip(rng: np.random.Generator, index: int, fps: float) -> tuple[Clip, np.ndarray]:
    """Human clip ``index`` (the action cycles with it) and its contacts (T, 4) per ``SMPL22.feet``."""
    action = HUMAN_ACTIONS[index % len(HUMAN_ACTIONS)]
    body = HumanBody.sample(rng)
    open_duration_s = _draw_open_durations(rng).get(action, 0.0)
    moods = ("neutral",) * NEUTRAL_WEIGHT + MOODS.get(action, ())
    style_name = moods[rng.integers(len(moods))]
    ctx = HumanContext(rng, fps, body, style_name, STYLES[style_name], open_duration_s)
    motion = HUMAN_ACTION_FUNCTIONS[action](ctx)
    channels, timeline = motion.channels, motion.channels.timeline

    # root path and footfalls
    padded_seconds, frames = timeline.padded_seconds, timeline.frames
    phase = channels.phase if channels.phase is not None else channels.gait.phase(padded_seconds)
    path = RootPath.integrate(padded_seconds, timeline.pad_frames, channels.velocity, channels.yaw_rate)
    feet = foot_targets(padded_seconds, frames, phase, channels.gait, channels.activity, path, body.neutral_feet)
    x, z, heading = path.at(timeline.seconds)
    dx, dz = rotate_by_heading(feet.yaw, channels.tip_offset[..., 0], channels.tip_offset[..., 2])
    tips = feet.tips + np.stack((dx, channels.tip_offset[..., 1], dz), -1)
    foot_pitch, contact = feet.pitch + channels.extra_pitch, feet.contact & ~channels.lifted
    dx, dz = rotate_by_heading(heading, channels.shift[:, 0], channels.shift[:, 1])
    root_xz = torch.as_tensor(np.stack((x + dx, z + dz), -1))

    # body, then legs
    rotations = _body_rotations(body.offsets, heading, channels.pelvis, channels.spine, channels.head, channels.arms)
    ankle_rotations = quat_mul(axis_rotation("y", feet.yaw), axis_rotation("x", foot_pitch))
    rotations, positions = solve_legs(
        SMPL22, body.offsets, HUMAN_LEGS, rotations, root_xz, channels.height, torch.as_tensor(tips), ankle_rotations,
        torch.as_tensor(contact), torch.as_tensor(channels.poles), max(1, round(0.12 * fps)),
    )  # fmt: skip
    # contacts per skeleton.feet joint: the ankle (heel) while the foot is flat, the toe all stance
    flat = contact & (foot_pitch < 1e-3)
    contacts = np.stack((flat[:, 0], contact[:, 0], flat[:, 1], contact[:, 1]), -1)
    texts = captions.sample_captions(rng, captions.PEOPLE, motion.caption)
    labels = {"action": action, "style": style_name, **motion.labels}
    return make_clip(SMPL22, "human", index, action, fps, rotations, positions, body.offsets, texts, labels), contacts
