"""A constraints file (JSON) read, checked and resolved into the tensor-level ``omg.lit.control.Control`` a
diffusion model samples with (``omg generate --constraints``, ``omg serve``'s ``constraints``).

The format is docs/guide/control.md's: ``keyframes`` (a pose at a time: joint positions, or a frame of a BVH /
``.npy`` take retargeted onto the model's skeleton), ``targets`` (a joint at a time or over a span, some axes),
``waypoints`` (the root on the ground, at times or with free timing) and a dense ``path``, ``facing``,
``contacts`` (given feet planted over spans, ``"model"``: the model's own contact channels, ``"ground"``: the
feet each estimate puts on the ground); each constraint
may carry ``weight`` and ``tolerance``. Positions are world metres, Y up, in the frame the model generates in:
the motion's first frame has its root above the XZ origin, facing +Z. Every error is one line naming the
constraint (``targets[1].joint``), and nothing is sampled or written after one.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from omg.errors import UsageError
from omg.generation.protocol import GenerationCard
from omg.lit.control import Control
from omg.motion.base import Representation
from omg.skeleton import Skeleton, get_skeleton

KINDS = ("keyframes", "targets", "waypoints", "path", "facing", "contacts")
RESERVED = ("timeline", "parts")  # the prompt timeline's and the body-part composition's keys
MET_MARGIN = 0.05  # metres beyond its tolerance at which a constraint counts as not met (a warning)
# how hard to steer, and how smoothly: the file's "steering"
STEERING = ("iterations", "final_iterations", "smooth", "curvature", "inpaint")


def contact_sources(representation: Representation) -> tuple[str, ...]:
    """What a constraints file's ``contacts`` may name for a model of ``representation`` (its card's
    ``contacts``): "model" where it has contact channels, "ground" where its skeleton has feet."""
    channels = representation.foot_contacts(torch.zeros(1, 1, representation.dim)) is not None
    return ("model",) * channels + ("ground",) * bool(representation.skeleton.feet)


def read_constraints(source: Path | str | dict, card: GenerationCard, frames: int, what: str = "--constraints",
                     allow_files: bool = True) -> tuple[Control, dict]:
    """(the resolved ``Control`` for one motion of ``frames`` frames on ``card``'s skeleton, the constraints as
    given) from a JSON file or an already parsed object; one line per error. ``allow_files``: keyframes may name
    motion files (not in a request: the server reads no file a client names)."""
    folder = Path(".")
    if isinstance(source, dict):
        spec = source
    else:
        from omg.files import read_text

        path = Path(source)
        folder = path.parent
        try:
            spec = json.loads(read_text(path, what), parse_constant=_refuse_constant(f"{what} {path}"))
        except json.JSONDecodeError as e:
            raise UsageError(f"{what} {path}: not JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
        what = f"{what} {path}"
    if not isinstance(spec, dict):
        raise UsageError(f"{what}: expected a JSON object with any of {', '.join(KINDS)}")
    if reserved := [k for k in RESERVED if k in spec]:
        raise UsageError(f"{what}: {reserved[0]!r} is a prompt timeline's key: use --timeline for it")
    if unknown := sorted(set(spec) - set(KINDS) - {"steering"}):
        raise UsageError(f"{what}: unknown key {unknown[0]!r}; a constraints file has {', '.join(KINDS)} and steering")
    if not card.constraints:
        raise UsageError(f"{what}: this {card.family} model takes no constraints (its generation card lists none)")
    if refused := [k for k in KINDS if k in spec and k not in card.constraints]:
        raise UsageError(f"{what}: this model takes no {refused[0]}; it takes {', '.join(card.constraints)}")
    builder = _Builder(get_skeleton(card.skeleton), card, frames, what, folder, allow_files)
    for kind in KINDS:
        if kind in spec:
            getattr(builder, f"add_{kind}")(spec[kind])
    return builder.control(_steering(spec.get("steering", {}), what)), spec


def _refuse_constant(what: str):
    def refuse(name: str) -> float:
        raise UsageError(f"{what}: holds {name}, which is no position; give finite numbers")
    return refuse


def _steering(given: Any, what: str) -> dict[str, Any]:
    if not isinstance(given, dict) or set(given) - set(STEERING):
        raise UsageError(f"{what}: steering is an object of {', '.join(STEERING)}")
    out: dict[str, Any] = {}
    for key, value in given.items():
        if key == "inpaint":
            if not isinstance(value, bool):
                raise UsageError(f"{what}: steering.inpaint must be true or false")
            out[key] = value
        elif key == "smooth":
            out[key] = _number(value, f"{what}: steering.smooth", low=0.0, high=60.0)
        elif key == "curvature":
            out[key] = _number(value, f"{what}: steering.curvature", low=0.0, high=1.0)
        else:
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 1000:
                raise UsageError(f"{what}: steering.{key} must be an integer in 0..1000, got {value!r}")
            out[key] = value
    return out


def _number(value: Any, where: str, low: float = -math.inf, high: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UsageError(f"{where} must be a finite number, got {value!r}")
    if not low <= value <= high:
        raise UsageError(f"{where} must be in [{low:g}, {high:g}], got {value!r}")
    return float(value)


def _vector(value: Any, size: int, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != size:
        raise UsageError(f"{where} must be a list of {size} numbers (metres), got {value!r}")
    return np.array([_number(v, where) for v in value], dtype=np.float32)


class _Builder:
    """Accumulates the resolved tensors of one motion, one constraint at a time."""

    def __init__(self, skeleton: Skeleton, card: GenerationCard, frames: int, what: str, folder: Path,
                 allow_files: bool):
        J = skeleton.num_joints
        self.skeleton, self.card, self.frames, self.what, self.folder = skeleton, card, frames, what, folder
        self.allow_files = allow_files
        self.targets = np.zeros((frames, J, 3), np.float32)
        self.axes = np.zeros((frames, J, 3), bool)
        self.weights = np.zeros((frames, J), np.float32)
        self.tolerance = np.zeros((frames, J), np.float32)
        self.groups = np.full((frames, J), -1, np.int64)
        self.names: list[str] = []
        self.contacts: np.ndarray | None = None
        self.own_contacts = False
        self.ground_contacts = False
        self.facing_: np.ndarray | None = None

    # -- pieces -----------------------------------------------------------------------------------------------
    def items(self, value: Any, kind: str) -> list[tuple[str, dict]]:
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise UsageError(f"{self.what}: {kind} must be a list of objects")
        return [(f"{kind}[{i}]", v) for i, v in enumerate(value)]

    def keys(self, item: dict, where: str, allowed: tuple[str, ...]) -> None:
        if unknown := sorted(set(item) - set(allowed) - {"weight", "tolerance"}):
            raise UsageError(f"{self.what}: {where} has no key {unknown[0]!r}; it takes "
                             f"{', '.join((*allowed, 'weight', 'tolerance'))}")

    def frame(self, seconds: Any, where: str) -> int:
        duration = self.frames / self.card.fps
        seconds = _number(seconds, f"{self.what}: {where}")
        if not 0 <= seconds <= duration:
            raise UsageError(f"{self.what}: {where} {seconds:g} s is outside the motion (0..{duration:g} s)")
        return min(round(seconds * self.card.fps), self.frames - 1)

    def span(self, item: dict, where: str) -> range:
        if ("time" in item) == ("span" in item):
            raise UsageError(f"{self.what}: {where} needs a time (seconds) or a span [start, end], one of them")
        if "time" in item:
            f = self.frame(item["time"], f"{where}.time")
            return range(f, f + 1)
        span = item["span"]
        if not isinstance(span, list) or len(span) != 2:
            raise UsageError(f"{self.what}: {where}.span must be [start, end] in seconds, got {span!r}")
        start, end = self.frame(span[0], f"{where}.span start"), self.frame(span[1], f"{where}.span end")
        if end < start:
            raise UsageError(f"{self.what}: {where}.span ends before it starts ({span[0]} > {span[1]})")
        return range(start, end + 1)

    def joint(self, name: Any, where: str) -> int:
        if not isinstance(name, str) or name not in self.skeleton.names:
            raise UsageError(f"{self.what}: {where} {name!r} is not a joint of {self.skeleton.name} "
                             f"({', '.join(self.skeleton.names)})")
        return self.skeleton.names.index(name)

    def strength(self, item: dict, where: str) -> tuple[float, float]:
        weight = _number(item.get("weight", 1.0), f"{self.what}: {where}.weight", 0.0, 1e6)
        tolerance = _number(item.get("tolerance", 0.0), f"{self.what}: {where}.tolerance", 0.0, 100.0)
        return weight, tolerance

    def put(self, frames, joint: int, position: np.ndarray, axes: np.ndarray, where: str, item: dict) -> None:
        weight, tolerance = self.strength(item, where)
        if where not in self.names:
            self.names.append(where)
        for f in frames:
            self.targets[f, joint] = np.where(axes, position, self.targets[f, joint])
            self.axes[f, joint] |= axes
            self.weights[f, joint], self.tolerance[f, joint] = weight, tolerance
            self.groups[f, joint] = self.names.index(where)

    # -- kinds ------------------------------------------------------------------------------------------------
    def add_keyframes(self, value: Any) -> None:
        for where, item in self.items(value, "keyframes"):
            self.keys(item, where, ("time", "joints", "positions", "file", "frame", "joint_map", "root"))
            given = [k for k in ("joints", "positions", "file") if k in item]
            if len(given) != 1:
                raise UsageError(f"{self.what}: {where} needs one of joints ({{name: [x, y, z]}}), positions "
                                 f"([[x, y, z]] per joint) or file (a BVH or .npy take, with frame)")
            frame = self.frame(item.get("time"), f"{where}.time") if "time" in item else None
            if frame is None:
                raise UsageError(f"{self.what}: {where} needs a time (seconds)")
            J = self.skeleton.num_joints
            if "joints" in item:
                if not isinstance(item["joints"], dict) or not item["joints"]:
                    raise UsageError(f"{self.what}: {where}.joints must be an object of joint name -> [x, y, z]")
                pose = {self.joint(n, f"{where}.joints"): _vector(p, 3, f"{self.what}: {where}.joints.{n}")
                        for n, p in item["joints"].items()}
            elif "positions" in item:
                rows = item["positions"]
                if not isinstance(rows, list) or len(rows) != J:
                    raise UsageError(f"{self.what}: {where}.positions must list [x, y, z] for each of the "
                                     f"{J} joints of {self.skeleton.name}")
                pose = {j: _vector(p, 3, f"{self.what}: {where}.positions[{j}]") for j, p in enumerate(rows)}
            else:
                pose = dict(enumerate(self.pose_from_file(item, where)))
            if "root" in item:  # the pose moved on the ground so that its root is there
                root = _vector(item["root"], 2, f"{self.what}: {where}.root")
                if 0 not in pose:
                    raise UsageError(f"{self.what}: {where}.root moves the pose by its root: give the root's joint")
                shift = np.array([root[0] - pose[0][0], 0.0, root[1] - pose[0][2]], np.float32)
                pose = {j: p + shift for j, p in pose.items()}
            for j, p in pose.items():
                self.put(range(frame, frame + 1), j, p, np.ones(3, bool), where, item)

    def pose_from_file(self, item: dict, where: str) -> np.ndarray:
        """(J, 3) a frame of a take retargeted onto the model's skeleton, placed as the take places it relative to
        its first frame in the model's world (root above the origin, facing +Z)."""
        if not self.allow_files:
            raise UsageError(f"{self.what}: {where}.file: a request names no file; give joints or positions")
        name = item["file"]
        if not isinstance(name, str) or not name:
            raise UsageError(f"{self.what}: {where}.file must be a path")
        path = Path(name) if Path(name).is_absolute() else self.folder / name
        joint_map = item.get("joint_map")
        if joint_map is not None and not isinstance(joint_map, str):
            raise UsageError(f"{self.what}: {where}.joint_map must be a joint map's name or YAML file")
        try:
            poses = take_poses(path, self.card, joint_map, f"{self.what}: {where}.file")
        except UsageError as e:  # a rig no joint map fits: said of this keyframe
            message = str(e)
            raise UsageError(message if message.startswith(self.what) else f"{self.what}: {where}.file: {message}"
                             ) from None
        index = item.get("frame", 0)
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(poses):
            raise UsageError(f"{self.what}: {where}.frame must be a frame of the take (0..{len(poses) - 1}), "
                             f"got {index!r}")
        return poses[index]

    def add_targets(self, value: Any) -> None:
        for where, item in self.items(value, "targets"):
            self.keys(item, where, ("joint", "time", "span", "position", "axes"))
            joint = self.joint(item.get("joint"), f"{where}.joint")
            axes_given = item.get("axes", "xyz")
            if not isinstance(axes_given, str) or not axes_given or set(axes_given) - set("xyz"):
                raise UsageError(f"{self.what}: {where}.axes must name some of x, y, z (e.g. \"y\"), got "
                                 f"{axes_given!r}")
            axes = np.array([a in axes_given for a in "xyz"])
            position = item.get("position")
            if not isinstance(position, list) or len(position) != 3:
                raise UsageError(f"{self.what}: {where}.position must be [x, y, z] metres (null on a free axis)")
            position = np.array([_number(v, f"{self.what}: {where}.position[{i}]") if axes[i] else 0.0
                                 for i, v in enumerate(position)], np.float32)  # a free axis may be null
            self.put(self.span(item, where), joint, position, axes, where, item)

    def add_waypoints(self, value: Any) -> None:
        items = self.items(value, "waypoints")
        points, times = [], []
        for where, item in items:
            self.keys(item, where, ("position", "time"))
            points.append(_vector(item.get("position"), 2, f"{self.what}: {where}.position"))
            times.append(self.frame(item["time"], f"{where}.time") if "time" in item else None)
        # free timing: a waypoint without a time is reached at the share of the path's length it lies at, between
        # its timed neighbours (the start at the origin; after the last timed one, the motion's end)
        anchors = [(-1, 0, np.zeros(2, np.float32))] + [(i, t, points[i]) for i, t in enumerate(times) if t is not None]
        if times and times[-1] is None:
            anchors.append((len(points), self.frames - 1, None))
        for (a, start, origin), (b, end, _) in zip(anchors, anchors[1:]):
            chain = [origin] + points[a + 1 : min(b + 1, len(points))]
            lengths = np.cumsum([0.0] + [float(np.linalg.norm(q - p)) for p, q in zip(chain, chain[1:])])
            for k in range(a + 1, min(b, len(points))):
                times[k] = round(start + (end - start) * lengths[k - a] / max(lengths[-1], 1e-9))
        for i, ((where, item), point, frame) in enumerate(zip(items, points, times)):
            if i and times[i - 1] > frame:
                raise UsageError(f"{self.what}: {where} comes before the waypoint listed ahead of it: give times "
                                 "in order")
            self.put(range(frame, frame + 1), 0, np.array([point[0], 0.0, point[1]], np.float32),
                     np.array([True, False, True]), where, item)

    def add_path(self, value: Any) -> None:
        where = "path"
        if not isinstance(value, dict):
            raise UsageError(f"{self.what}: path must be an object with points [[x, z], ...] and an optional span")
        self.keys(value, where, ("points", "span"))
        points = value.get("points")
        if not isinstance(points, list) or len(points) < 2:
            raise UsageError(f"{self.what}: path.points must list 2 or more [x, z] points on the ground")
        xz = np.stack([_vector(p, 2, f"{self.what}: path.points[{i}]") for i, p in enumerate(points)])
        frames = self.span(value, where) if "span" in value else range(self.frames)
        # the points are spread evenly in time over the span, the root between them on straight lines
        at = np.linspace(0, len(xz) - 1, len(frames))
        x, z = np.interp(at, np.arange(len(xz)), xz[:, 0]), np.interp(at, np.arange(len(xz)), xz[:, 1])
        for f, xi, zi in zip(frames, x, z):
            self.put(range(f, f + 1), 0, np.array([xi, 0.0, zi], np.float32), np.array([True, False, True]), where,
                     value)

    def add_facing(self, value: Any) -> None:
        if not self.skeleton.face_joints:
            raise UsageError(f"{self.what}: facing: skeleton {self.skeleton.name} has no hips and shoulders to face by")
        for where, item in self.items(value, "facing"):
            self.keys(item, where, ("time", "span", "direction"))
            direction = _vector(item.get("direction"), 2, f"{self.what}: {where}.direction")
            norm = float(np.linalg.norm(direction))
            if norm == 0:
                raise UsageError(f"{self.what}: {where}.direction [0, 0] points nowhere; give [x, z] on the ground")
            if self.facing_ is None:
                self.facing_ = np.zeros((self.frames, 2), np.float32)
            for f in self.span(item, where):
                self.facing_[f] = direction / norm

    def add_contacts(self, value: Any) -> None:
        """``"model"`` (the model's own contact channels), ``"ground"`` (the feet each estimate puts on the
        ground), or a list of given spans ``{joint, span}`` and those two words."""
        feet = self.skeleton.feet
        if not feet:
            raise UsageError(f"{self.what}: contacts: skeleton {self.skeleton.name} names no feet")
        listed = [value] if isinstance(value, str) else value
        if not isinstance(listed, list):
            listed = [None]  # refused below, with what it takes
        for index, item in enumerate(listed):
            where = "contacts" if isinstance(value, str) else f"contacts[{index}]"
            if item in ("model", "ground") and item not in self.card.contacts:
                if item == "model":
                    raise UsageError(f"{self.what}: {where}: \"model\" needs contact channels, which representation "
                                     f"{self.card.representation} has none of: give the feet's spans or \"ground\"")
                raise UsageError(f"{self.what}: {where}: this model holds no \"{item}\" feet; give the feet's spans")
            if item == "model":
                self.own_contacts = True
            elif item == "ground":
                self.ground_contacts = True
            elif isinstance(item, dict):
                self.keys(item, where, ("joint", "time", "span"))
                joint = self.joint(item.get("joint"), f"{where}.joint")
                if joint not in feet:
                    names = ", ".join(self.skeleton.names[j] for j in feet)
                    raise UsageError(f"{self.what}: {where}.joint {self.skeleton.names[joint]!r} is no foot ({names})")
                if self.contacts is None:
                    self.contacts = np.zeros((self.frames, len(feet)), bool)
                for f in self.span(item, where):
                    self.contacts[f, feet.index(joint)] = True
            else:
                raise UsageError(f"{self.what}: {where} is none of \"model\" (the model's own contact channels), "
                                 "\"ground\" (the feet each estimate puts on the ground) or {joint, span}")

    def control(self, steering: dict[str, Any]) -> Control:
        def tensor(a: np.ndarray | None) -> torch.Tensor | None:
            return None if a is None else torch.from_numpy(a)[None]

        return Control(targets=tensor(self.targets), axes=tensor(self.axes), weights=tensor(self.weights),
                       tolerance=tensor(self.tolerance), groups=tensor(self.groups), names=tuple(self.names),
                       contacts=tensor(self.contacts), own_contacts=self.own_contacts,
                       ground_contacts=self.ground_contacts, fps=self.card.fps, facing=tensor(self.facing_),
                       **steering)


def take_poses(path: Path, card: GenerationCard, joint_map: str | None, what: str) -> np.ndarray:
    """(T, J, 3) every frame of a take (BVH, ASF/AMC, DeepMimic, or a ``.npy`` of the model's joints) retargeted
    onto ``card``'s skeleton at its fps by the importers, placed as the take places it relative to its first frame
    in the model's world (root above the origin, facing +Z): the poses a keyframe's ``file`` and ``frame`` pick
    from (``omg serve``'s ``/v1/keyframes`` too). ``what`` names the file in the one-line errors."""
    from omg.generation.read import read_source_motion
    from omg.motion import Clip, get_representation

    skeleton = get_skeleton(card.skeleton)
    take = read_source_motion(path, skeleton, card.fps, joint_map, what)
    positions = take.positions if isinstance(take, Clip) else take
    J = skeleton.num_joints
    if positions.ndim != 3 or positions.shape[1:] != (J, 3) or len(positions) < 1:
        where = f"{what} {path}" if what else str(path)
        raise UsageError(f"{where}: a .npy keyframe holds {skeleton.name} joint positions (T, {J}, 3), got shape "
                         f"{positions.shape}")
    representation = get_representation(card.representation, skeleton)
    if hasattr(representation, "canonicalize") and len(positions) >= 2:
        placed = representation.canonicalize(positions)  # the frame the features describe (HumanML3D's)
    else:
        placed = positions - positions[:1, :1] * np.array([1.0, 0.0, 1.0])
    return np.asarray(placed, np.float32)


def unmet(errors: dict[str, float], control: Control) -> dict[str, float]:
    """The constraints of one motion whose worst error is beyond their tolerance by more than ``MET_MARGIN``."""
    tolerance = {name: float(control.tolerance[control.groups == i].max()) if (control.groups == i).any() else 0.0
                 for i, name in enumerate(control.names)}
    return {name: e for name, e in errors.items() if e > tolerance.get(name, 0.0) + MET_MARGIN}
