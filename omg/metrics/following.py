"""Prompt following measured by what the motion does: no learned judge, only joints.

A prompt with known targets ("a person waves the left hand" -> ``{hand: left, action: wave}``)
passes when a generated motion does each part of it. Every test reads joint positions (T, J, 3)
on a skeleton with SMPL-22's joint names (+Y up, the body's left along +X when it faces +Z) and
is stated relative to the body itself:

- lengths in body sizes (``body_size``: the ankle -> knee -> hip -> pelvis -> spine -> head chain,
  a bone-length sum that no pose changes), times in seconds (the frame rate is an argument);
- directions in the body's own frame: its facing (``facing``) is the horizontal normal of the
  hips and shoulders, as HumanML3D's canonical frame takes it.

The targets (each part of a prompt is one mapping; a prompt passes when all of its parts do):

- ``{hand: left|right|both|either, action: raise|wave}``: *raise*: the wrist rises above the
  head joint at some frame; *wave*: while the forearm points up (wrist above elbow) the wrist
  sways sideways in the body's frame, relative to the neck, over a path of at least
  ``WAVE_PATH`` body sizes and at least ``WAVE_SWAYS`` times the width it spans (a wave goes
  back and forth; one sweep spans its own path). A one-sided target also needs the other hand
  not to do it: "waves the left hand" fails when both wave, which is how a side mix-up shows.
- ``{turn: left|right|around, angle: degrees}``: the facing turns between the first and the
  last quarter second by at least ``MIN_TURN`` degrees towards that side (left is
  counter-clockwise seen from above); with ``angle``, by ``angle`` ± ``TURN_TOLERANCE``;
  ``around``: 180° ± ``TURN_TOLERANCE`` either way.
- ``{travel: forward|backward|left|right}``: the root's net horizontal displacement, at least
  ``MIN_DISPLACEMENT`` body sizes, points within ``FORWARD_CONE``° of the initial facing
  (forward), of its reverse (backward), or at least ``SIDE_ANGLE``° to that side of it (left,
  right: sideways or diagonally).
- ``{pace: still|moving|walk|run}``: *moving* when the root's horizontal speed over half-second
  steps averages at least ``MOVING_SPEED`` body sizes per second, *still* otherwise; *run* is
  moving with no foot on the ground (``omg.kinematics.ground_contacts``) in at least
  ``RUN_FLIGHT`` of the frames, *walk* moving with less.

The thresholds are set on real takes (Bandai-Namco datasets 1 and 2) and are scored there:
real clips of every class pass their own targets, the figure that bounds the check's error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric

from omg.errors import UsageError
from omg.files import read_text
from omg.kinematics import ground_contacts
from omg.metrics.base import EvalBatch, GenerationMetric
from omg.registry import METRICS
from omg.skeleton import Skeleton, get_skeleton

WAVE_PATH = 0.5  # body sizes of sideways wrist path while the forearm is up
WAVE_SWAYS = 2.5  # path over spanned width: more than one back-and-forth
MIN_TURN = 45.0  # degrees
TURN_TOLERANCE = 45.0  # degrees around a named angle
MIN_DISPLACEMENT = 0.25  # body sizes: less has no direction
FORWARD_CONE = 30.0  # degrees
SIDE_ANGLE = 15.0  # degrees off the facing that make a path go to one side
MOVING_SPEED = 0.2  # body sizes per second
RUN_FLIGHT = 1 / 3  # fraction of frames with no foot on the ground
END_SECONDS = 0.25  # the start and end facings are averaged over this long

HANDS = ("left", "right", "both", "either")
ACTIONS = ("raise", "wave")
TURNS = ("left", "right", "around")
TRAVELS = ("forward", "backward", "left", "right")
PACES = ("still", "moving", "walk", "run")
KINDS = ("hand", "turn", "travel", "pace")  # what a part tests: the one of these keys it has
CATEGORIES = ("plain", "sidedness", "paraphrases", "combinations")
DEFAULT_PROMPTS = Path(__file__).with_name("following.yaml")

_UP = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)


class Joints:
    """The joints a test reads, by name, on any skeleton that has SMPL-22's names."""

    def __init__(self, skeleton: str | Skeleton = "smpl22"):
        skeleton = get_skeleton(skeleton)
        try:
            self.index = {name: skeleton.index(name) for name in (
                "pelvis", "spine1", "spine2", "spine3", "neck", "head", "left_hip", "right_hip", "left_knee",
                "right_knee", "left_ankle", "right_ankle", "left_shoulder", "right_shoulder", "left_elbow",
                "right_elbow", "left_wrist", "right_wrist")}
        except KeyError as e:
            raise UsageError(f"prompt following reads SMPL-22's joints by name: {e.args[0]}") from None
        self.feet = list(skeleton.feet)
        if not self.feet:
            raise UsageError(f"skeleton {skeleton.name!r} names no feet; prompt following needs them for the pace")

    def __getitem__(self, name: str) -> int:
        return self.index[name]


def _window(fps: float, frames: int) -> int:
    return max(1, min(frames, round(END_SECONDS * fps)))


def body_size(joints: Tensor, at: Joints) -> float:
    """Median over frames of the ankle -> knee -> hip -> pelvis -> spine -> neck -> head bone
    lengths (both legs averaged): the body's size, whatever its pose."""
    def chain(names: Sequence[str]) -> Tensor:
        idx = [at[n] for n in names]
        return (joints[:, idx[1:]] - joints[:, idx[:-1]]).norm(dim=-1).sum(-1)  # (T,)

    trunk = chain(("pelvis", "spine1", "spine2", "spine3", "neck", "head"))
    legs = (chain(("left_ankle", "left_knee", "left_hip", "pelvis"))
            + chain(("right_ankle", "right_knee", "right_hip", "pelvis"))) / 2
    return float((trunk + legs).median())


def facing(joints: Tensor, at: Joints) -> Tensor:
    """(T, J, 3) -> (T, 3) unit horizontal facing: (the right -> left vector across the hips and
    the shoulders) x up, which points forward (+Z for a body facing +Z with its left at +X)."""
    across = (joints[:, at["left_hip"]] - joints[:, at["right_hip"]]
              + joints[:, at["left_shoulder"]] - joints[:, at["right_shoulder"]])  # (T, 3) towards the left
    forward = torch.linalg.cross(across, _UP.to(across).expand_as(across))  # left x up = forward
    forward[:, 1] = 0
    return forward / forward.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def _left_of(forward: Tensor) -> Tensor:
    """(..., 3) horizontal facing -> (..., 3) the body's left: up x forward."""
    return torch.linalg.cross(_UP.to(forward).expand_as(forward), forward)


def turn_angle(joints: Tensor, fps: float, at: Joints) -> float:
    """Degrees the facing turns from the first to the last quarter second; positive to the left
    (counter-clockwise seen from above)."""
    f = facing(joints, at)
    yaw = torch.atan2(f[:, 0], f[:, 2])  # (T,) 0 facing +Z, growing as the body turns left (to +X)
    step = torch.remainder(yaw[1:] - yaw[:-1] + math.pi, 2 * math.pi) - math.pi  # unwrapped per frame
    yaw = torch.cat([yaw[:1], yaw[:1] + step.cumsum(0)])
    w = _window(fps, len(yaw))
    return math.degrees(float(yaw[-w:].mean() - yaw[:w].mean()))


def displacement(joints: Tensor, fps: float, at: Joints) -> tuple[float, float]:
    """The root's net horizontal displacement (forward, left) in body sizes, in the frame of the
    facing of the first quarter second."""
    w = _window(fps, len(joints))
    forward = facing(joints[:w], at).mean(0)
    forward = forward / forward.norm().clamp_min(1e-9)
    root = joints[:, at["pelvis"]]
    step = root[-w:].mean(0) - root[:w].mean(0)
    size = body_size(joints, at)
    return float(step @ forward) / size, float(step @ _left_of(forward)) / size


def root_speed(joints: Tensor, fps: float, at: Joints) -> float:
    """Mean horizontal root speed over half-second steps, in body sizes per second (the steps
    smooth out the sway of each stride)."""
    k = max(1, min(len(joints) - 1, round(0.5 * fps)))
    root = joints[:, at["pelvis"], [0, 2]]
    if len(root) < 2:
        return 0.0
    speed = (root[k:] - root[:-k]).norm(dim=-1) * fps / k
    return float(speed.mean()) / body_size(joints, at)


def flight_fraction(joints: Tensor, fps: float, at: Joints) -> float:
    """Fraction of frames with no foot joint on the ground."""
    contact = ground_contacts(joints, at.feet, fps)  # (T, F)
    return float((~contact.any(-1)).double().mean())


def raises(joints: Tensor, side: str, at: Joints) -> bool:
    """The ``side`` wrist rises above the head joint at some frame."""
    return bool((joints[:, at[f"{side}_wrist"], 1] > joints[:, at["head"], 1]).any())


def wave_sway(joints: Tensor, side: str, at: Joints) -> tuple[float, float]:
    """(path, width) in body sizes of the ``side`` wrist's sideways motion relative to the neck,
    in the body's own frame, over the frames where the forearm points up."""
    wrist = joints[:, at[f"{side}_wrist"]]
    up = wrist[:, 1] > joints[:, at[f"{side}_elbow"], 1]  # (T,)
    lateral = ((wrist - joints[:, at["neck"]]) * _left_of(facing(joints, at))).sum(-1)  # (T,)
    both_up = up[1:] & up[:-1]
    if not both_up.any():
        return 0.0, 0.0
    size = body_size(joints, at)
    path = float(((lateral[1:] - lateral[:-1]).abs() * both_up).sum()) / size
    held = lateral[up]
    return path, float(held.max() - held.min()) / size


def waves(joints: Tensor, side: str, at: Joints) -> bool:
    path, width = wave_sway(joints, side, at)
    return path >= WAVE_PATH and path >= WAVE_SWAYS * width


def check_target(target: dict[str, Any], where: str = "target") -> str:
    """The kind of a target (``KINDS``), or a UsageError naming what is wrong with it."""
    kinds = [k for k in KINDS if k in target]
    if len(kinds) != 1:
        raise UsageError(f"{where}: a target names exactly one of {', '.join(KINDS)}, got {dict(target)!r}")
    kind = kinds[0]
    allowed = {"hand": {"hand", "action"}, "turn": {"turn", "angle"}, "travel": {"travel"}, "pace": {"pace"}}[kind]
    if extra := set(target) - allowed:
        raise UsageError(f"{where}: {kind} targets take {', '.join(sorted(allowed))}, not {', '.join(sorted(extra))}")
    values = {"hand": HANDS, "turn": TURNS, "travel": TRAVELS, "pace": PACES}[kind]
    if target[kind] not in values:
        raise UsageError(f"{where}: {kind} must be one of {', '.join(values)}, got {target[kind]!r}")
    if kind == "hand" and target.get("action") not in ACTIONS:
        raise UsageError(f"{where}: a hand target needs action: {' or '.join(ACTIONS)}, got {target.get('action')!r}")
    if kind == "turn" and "angle" in target and not (isinstance(target["angle"], int | float) and target["angle"] > 0):
        raise UsageError(f"{where}: angle is a positive number of degrees, got {target['angle']!r}")
    return kind


def passes(joints: Tensor, target: dict[str, Any], fps: float, at: Joints | None = None) -> bool:
    """Whether a motion (T, J, 3) does one target (see the module docstring)."""
    at = at or Joints()
    joints = joints.detach().double().cpu()
    kind = check_target(target)
    if kind == "hand":
        test = raises if target["action"] == "raise" else waves
        left, right = test(joints, "left", at), test(joints, "right", at)
        return {"left": left and not right, "right": right and not left, "both": left and right,
                "either": left or right}[target["hand"]]
    if kind == "turn":
        angle = turn_angle(joints, fps, at)
        if target["turn"] == "around":
            return abs(abs(angle) - 180.0) <= TURN_TOLERANCE
        signed = angle if target["turn"] == "left" else -angle
        if "angle" in target:
            return abs(signed - float(target["angle"])) <= TURN_TOLERANCE
        return signed >= MIN_TURN
    if kind == "travel":
        forward, left = displacement(joints, fps, at)
        if math.hypot(forward, left) < MIN_DISPLACEMENT:
            return False
        bearing = math.degrees(math.atan2(left, forward))  # 0 ahead, +90 to the left
        return {"forward": abs(bearing) <= FORWARD_CONE, "backward": abs(bearing) >= 180.0 - FORWARD_CONE,
                "left": SIDE_ANGLE <= bearing <= 180.0 - SIDE_ANGLE,
                "right": SIDE_ANGLE <= -bearing <= 180.0 - SIDE_ANGLE}[target["travel"]]
    moving = root_speed(joints, fps, at) >= MOVING_SPEED
    if target["pace"] in ("still", "moving"):
        return moving == (target["pace"] == "moving")
    running = flight_fraction(joints, fps, at) >= RUN_FLIGHT
    return moving and running == (target["pace"] == "run")


# -- the prompt set -----------------------------------------------------------------------------

def _read(path: Path) -> Any:
    import yaml

    text = read_text(path, "the prompt file")
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UsageError(f"the prompt file {path}: not valid YAML ({str(e).splitlines()[0]})") from None


def load_prompts(path: str | Path | None = None) -> list[dict[str, Any]]:
    """A prompt file: ``prompts: [{text, category, seconds, targets: [{...}, ...]}, ...]`` (YAML);
    the built-in set (``following.yaml`` beside this module) when ``path`` is None. Every entry is
    checked here, so a bad file fails before any sampling."""
    path = Path(path) if path is not None else DEFAULT_PROMPTS
    data = _read(path)
    entries = data.get("prompts") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise UsageError(f"{path}: expected `prompts:` with a list of {{text, category, seconds, targets}}")
    out = []
    for i, entry in enumerate(entries):
        where = f"{path}: prompts[{i}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("text"), str) or not entry["text"].strip():
            raise UsageError(f"{where}: each prompt is a mapping with a non-empty text")
        category = entry.get("category", "plain")
        if category not in CATEGORIES:
            raise UsageError(f"{where}: category must be one of {', '.join(CATEGORIES)}, got {category!r}")
        seconds = entry.get("seconds", 4.0)
        if not isinstance(seconds, int | float) or seconds <= 0:
            raise UsageError(f"{where}: seconds must be a positive number, got {seconds!r}")
        targets = entry.get("targets")
        if not isinstance(targets, list) or not targets or not all(isinstance(t, dict) for t in targets):
            raise UsageError(f"{where}: targets is a non-empty list of mappings, one per part of the prompt")
        for j, target in enumerate(targets):
            check_target(target, f"{where}.targets[{j}]")
        out.append({"text": entry["text"], "category": category, "seconds": float(seconds), "targets": targets})
    return out


def label_targets(path: str | Path | None = None) -> dict[str, list[dict[str, Any]]]:
    """The targets of each action label (a take's ``content``) under the prompt file's ``labels:``,
    for scoring real clips; the built-in file's when ``path`` is None."""
    path = Path(path) if path is not None else DEFAULT_PROMPTS
    table = (_read(path) or {}).get("labels") or {}
    for label, targets in table.items():
        for j, target in enumerate(targets):
            check_target(target, f"{path}: labels.{label}[{j}]")
    return table


# -- the metric ---------------------------------------------------------------------------------

@METRICS.register("following")
class PromptFollowing(GenerationMetric, Metric):
    """The fraction of motions that do what their prompt says, from the joints alone.

    Rows are fed with their clip labels. A row whose labels hold ``targets`` (a list of target
    mappings, see the module docstring) and ``following`` (its category: plain, sidedness,
    paraphrases, combinations) is scored: a prompt file's rows (``EvalCallback.prompts``). A row
    of a validation clip is scored by its ``label`` (a take's ``content``) where the prompt file's
    ``labels:`` table (``targets_file``; the built-in one by default) gives that value targets,
    as ``sidedness`` when a target names a side and ``plain`` otherwise; its real motion is then
    scored too (``real/following``: the check's own error on that set). Other rows are left out.

    ``compute()`` returns ``following`` (prompts whose every part passes, over all prompts),
    ``following/<category>``, ``following/parts`` and ``following/<category>/parts`` (parts
    passed over parts: a two-part prompt done by half is 0.5 there, 0 in ``following``) and
    ``following/<kind>`` (hand, turn, travel, pace) for what was fed.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False
    reference = True
    needs_joints = True
    needs_embeddings = False
    needs_real = False

    def __init__(self, skeleton: str | Skeleton = "smpl22", fps: float = 20.0, label: str = "content",
                 targets_file: str | None = None, **kwargs):
        super().__init__(**kwargs)
        if not fps > 0:
            raise UsageError(f"following: fps must be positive, got {fps}")
        self.at, self.fps, self.label = Joints(skeleton), float(fps), label
        self.label_targets = label_targets(targets_file)
        zeros = torch.zeros
        self.add_state("prompts_passed", zeros(len(CATEGORIES), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("prompts", zeros(len(CATEGORIES), dtype=torch.float64), dist_reduce_fx="sum")
        # parts by (category, kind): how many parts of a category's prompts pass shows whether a
        # two-part prompt gets one part right or none
        shape = (len(CATEGORIES), len(KINDS))
        self.add_state("parts_passed", zeros(shape, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("parts", zeros(shape, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, joints: Tensor, mask: Tensor | None, labels: Sequence[dict]) -> None:
        """joints: (B, T, J, 3); mask: (B, T) True on real frames; labels: each row's clip labels."""
        for b, label in enumerate(labels):
            targets, category = label.get("targets"), label.get("following", "plain")
            if not targets:
                targets = self.label_targets.get(str(label.get(self.label)))
                if not targets:
                    continue
                sided = any(v in ("left", "right") for t in targets for v in t.values())
                category = "sidedness" if sided else "plain"
            frames = int(mask[b].sum()) if mask is not None else joints.shape[1]
            category = CATEGORIES.index(category)
            verdicts = []
            for target in targets:
                kind = KINDS.index(check_target(target))
                verdicts.append(passes(joints[b, :frames], target, self.fps, self.at))
                self.parts[category, kind] += 1
                self.parts_passed[category, kind] += verdicts[-1]
            self.prompts[category] += 1
            self.prompts_passed[category] += all(verdicts)

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.joints(real), batch.mask, batch.labels or [])

    def compute(self) -> dict[str, Tensor]:
        total = self.prompts.sum()
        out = {"following": self.prompts_passed.sum() / total if total else torch.tensor(float("nan"))}
        for i, name in enumerate(CATEGORIES):
            if self.prompts[i]:
                out[f"following/{name}"] = self.prompts_passed[i] / self.prompts[i]
                out[f"following/{name}/parts"] = self.parts_passed[i].sum() / self.parts[i].sum()
        if self.parts.sum():
            out["following/parts"] = self.parts_passed.sum() / self.parts.sum()
        passed, parts = self.parts_passed.sum(0), self.parts.sum(0)  # (K,) by kind
        for k, name in enumerate(KINDS):
            if parts[k]:
                out[f"following/{name}"] = passed[k] / parts[k]
        return out
