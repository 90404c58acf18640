"""Retargeting any rig's motion (``RigMotion``) onto a model skeleton (smpl22, smal35) by joint names.

A joint map says which source joint each target joint sits on. It is a YAML file::

    target: smpl22            # the skeleton it maps onto
    category: human           # optional: the clips' category (default: human for smpl22, else animal)
    name: my_rig              # optional (default: the file's stem)
    joints:                   # target joint: source joint, every one written out
      pelvis: Hips
      left_hip: LeftUpLeg
      ...

The built-in maps are such files in ``omg/joint_maps/`` (the Bandai-Namco BVH rig, CMU's rigs:
cgspeed BVH in both namings and ASF/AMC, LaFAN1, 100STYLE, Mixamo-named rigs (``mixamorig:*``),
the DeepMimic humanoid -> smpl22; the MANN dog BVH
and the DeepMimic dog -> smal35), registered in ``omg.registry.JOINT_MAPS`` by name; a plugin
registers its own the same way (``JOINT_MAPS.register("my_rig", path_or_JointMap)``). Without
a map, the registered one whose source joints are all present is picked.

Source names are joint names, or ``<joint>_end`` for a joint's end site (BVH End Site,
DeepMimic body tip). Target joints left out are filled in:

- between two mapped joints of one of the target's kinematic chains, on the straight line
  between them at the template's length ratios (spine, neck, tail segments);
- past the last mapped joint of a chain (SMAL ears, tail tip; SMPL head on rigs without
  one) rigidly with their parent, at the template's rest offset scaled to the individual.

The root and the parent of every end effector must be mapped or filled in between mapped
joints. The output clip has constant bone lengths by construction: each target joint's
global rotation turns the template's rest bone directions onto the mapped directions
(parent -> child; the best fit where a joint has several children: ``omg.kinematics``'s
``positions_to_rotations`` aiming from the mapped places), and bone lengths are
measured on the source's rest pose (so individual proportions stay; ``height`` rescales).
The source's up axis is detected (pelvis above the feet) and turned to +Y, the floor y = 0
is put under the feet of contact frames (``omg.kinematics.ground_contacts``: slow and low),
and the motion is resampled to the requested fps before anything else.

The other direction, ``onto_rig``: a motion on a model skeleton written onto a user's rig (a BVH file,
or a skinned glTF or FBX character, read by ``read_rig``), with the same maps (detected from the rig's
names, or given). Mapped rig joints turn so that their bones follow the model's, from the rig's own rest
orientation; joints the model lacks keep the rotation the rig holds them in (a BVH rig's own frames:
``_rig_pose``, ``_joint_frames``, ``_fit_turns``); the root travels the model's path scaled to the rig's
leg length, on the rig's own ground (``_clearance``), and planted feet are pinned (``omg.io.contacts``),
each at its own height on the rig's clip (``_own_height``); a character (its bind pose a stance on its
mesh's soles) keeps its feet's slope (``_stance_pitches``) and stands each planted foot's sole on the
floor frame by frame (``_feet``, ``_foot_levels``). ``rig_round_trip`` measures import + export on a
rig's own clip (``omg bench rig``).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from omg.errors import UsageError
from omg.files import read_text
from omg.io.rig import RigMotion
from omg.kinematics import GROUND_CONTACT_SPEED, ground_contacts, kabsch, nearest_rotation, positions_to_rotations
from omg.motion.base import Clip
from omg.registry import JOINT_MAPS
from omg.rotations import (
    matrix_to_quat,
    quat_apply,
    quat_between,
    quat_conjugate,
    quat_identity,
    quat_mul,
    quat_to_matrix,
)
from omg.skeleton import Skeleton, get_skeleton


@dataclass(frozen=True)
class JointMap:
    name: str
    target: str  # a registered skeleton name
    joints: dict  # target joint -> source joint (or "<joint>_end")
    category: str = "human"

    def missing(self, source_names: Sequence[str]) -> list[str]:
        present = set(source_names)
        return [s for s in self.joints.values() if s not in present]


def load_joint_map(path: str | Path) -> JointMap:
    """A joint map from YAML (format in the module docstring; the built-in ones are in omg/joint_maps/)."""
    path = Path(path)
    try:
        data = yaml.safe_load(read_text(path, "joint map"))
    except yaml.YAMLError as e:
        raise UsageError(f"joint map {path}: not valid YAML ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("joints"), dict) or not data.get("target"):
        raise UsageError(
            f"joint map {path}: expected a mapping with 'target: SKELETON' and 'joints: {{target: source}}'"
        )
    if todo := [str(k) for k, v in data["joints"].items() if v is None or str(v) == TODO]:
        raise UsageError(f"joint map {path}: {todo[0]} is {TODO} (no joint of the rig was matched to it): write the "
                         "rig's joint it sits on, or delete the line to have it filled in between its neighbours")
    joints = {str(k): str(v) for k, v in data["joints"].items()}
    target = str(data["target"])
    category = str(data.get("category") or ("human" if target == "smpl22" else "animal"))
    return JointMap(str(data.get("name") or path.stem), target, joints, category)


@cache
def _load_registered(name: str, path: Path) -> JointMap:
    jmap = load_joint_map(path)
    return jmap if jmap.name == name else replace(jmap, name=name)


def _registered(name: str) -> JointMap:
    """The map registered in ``JOINT_MAPS`` as ``name`` (a YAML file's path, or a ``JointMap``), named ``name``."""
    entry = JOINT_MAPS.get(name)
    if isinstance(entry, JointMap):
        return entry if entry.name == name else replace(entry, name=name)
    if isinstance(entry, (str, Path)):
        return _load_registered(name, Path(entry))
    raise UsageError(f"joint map {name!r} is registered as a {type(entry).__name__}; register a YAML path or JointMap")


def registered_joint_maps() -> list[JointMap]:
    """Every map of the ``JOINT_MAPS`` registry (the built-in ones and those plugins add), by name."""
    return [_registered(name) for name in JOINT_MAPS.names()]


def get_joint_map(spec: str | Path | JointMap) -> JointMap:
    """A registered map by name, a YAML file, or the map itself."""
    if isinstance(spec, JointMap):
        return spec
    if str(spec) in JOINT_MAPS:
        return _registered(str(spec))
    if Path(spec).suffix.lower() in (".yaml", ".yml") or Path(spec).exists():
        return load_joint_map(spec)
    raise UsageError(f"unknown joint map {str(spec)!r}: give a YAML file or one of {', '.join(JOINT_MAPS.names())}")


def source_names(motion: RigMotion) -> list[str]:
    """Joint names, then end-site names: what joint maps can refer to."""
    return list(motion.names) + motion.end_site_names()


def detect_joint_map(motion: RigMotion, target: str | None = None) -> JointMap | None:
    """The registered map (for ``target``, or any) whose source joints are all in ``motion``; the one
    with most joints where several fit (the first by name on a tie); None where none does."""
    names = source_names(motion)
    fits = [m for m in registered_joint_maps() if (target is None or m.target == target) and not m.missing(names)]
    return max(fits, key=lambda m: len(m.joints), default=None)


def resolve_joint_map(motion: RigMotion, target: Skeleton, joint_map: str | Path | JointMap | None = None) -> JointMap:
    """The map to use for ``motion`` -> ``target``; one UsageError naming missing joints otherwise."""
    names = source_names(motion)
    where = motion.source or motion.name
    if joint_map is None:
        found = detect_joint_map(motion, target.name)
        if found is not None:
            return found
        candidates = [m for m in registered_joint_maps() if m.target == target.name]
        if not candidates:
            raise UsageError(f"{where}: no registered joint map targets {target.name!r}; pass joint_map=YAML")
        closest = min(candidates, key=lambda m: len(m.missing(names)))
        raise UsageError(
            f"{where}: cannot map the rig onto {target.name} (no registered map fits); closest {closest.name!r} "
            f"lacks joints {', '.join(closest.missing(names))}; pass joint_map=YAML (`omg joint-map {where}` "
            "starts one from the closest map)"
        )
    jmap = get_joint_map(joint_map)
    if jmap.target != target.name:
        raise UsageError(f"joint map {jmap.name!r} maps onto {jmap.target!r}, not {target.name!r}")
    missing = jmap.missing(names)
    if missing:
        raise UsageError(f"{where}: joint map {jmap.name!r} needs joints the file lacks: {', '.join(missing)}")
    return jmap


# a character's ground under its planted feet's soles: this quantile of their level, the lowest foot's each frame, so
# that most go up onto it (a knee bends) and few down (a straight knee cannot)
STANCE_GROUND = 0.8
# m: a planted foot of a BVH rig whose median height over its contacts is within this of its height on the rig's
# own planted frames stays as the model puts it (the two sets of planted frames alone move the human rows' by up
# to 0.11 cm: a clip's round trip comes back as it went); one further off is moved to within it
FOOT_TOLERANCE = 0.003
FIT_FRAMES = 240  # of a BVH rig's own frames, at most, that its pose and the turns its fits miss are measured on
TODO = "TODO"  # a scaffold's value for a target joint no joint of the rig was matched to
SIMILAR = 0.75  # difflib ratio of two names' cores above which a scaffold proposes a joint


def _side(name: str) -> str | None:
    """left/right from a joint name (LeftArm, Arm_L, l_arm, L_Arm, arm.l, LArm), else None."""
    base = name.rsplit(":", 1)[-1]
    for side, word, letter in (("left", "left", "l"), ("right", "right", "r")):
        if (word in base.lower() or re.search(rf"(^|[_.\s-]){letter}([_.\s-]|$)", base, re.I)
                or re.match(rf"{letter.upper()}(?=[A-Z])", base)):
            return side
    return None


def _core(name: str) -> str:
    """A joint name without namespace, side and separators, lower case: what two rigs' names share."""
    base = name.rsplit(":", 1)[-1]
    base = re.sub(r"(?i)left|right", "", base)
    base = re.sub(r"(^|[_.\s-])[lLrR](?=[_.\s-]|$)", "", base)
    base = re.sub(r"^[LR](?=[A-Z])", "", base)
    return re.sub(r"[^a-z0-9]", "", base.lower())


def _scaffold(jmap: JointMap, names: list[str], called: dict[str, set[str]],
              structure: dict[str, tuple[str, str]]) -> tuple[dict[str, str], dict[str, str]]:
    """``jmap``'s joints on a rig with joints ``names``: (target joint -> rig joint, target joint -> why it
    is a guess). The rig's joint of the map's name first, then what the rig's structure shows (for a map
    onto the skeleton ``structure`` is of), then the closest name to what the registered maps call it."""
    import difflib
    import json

    chosen = {joint: source for joint, source in jmap.joints.items() if source in names}
    guessed: dict[str, str] = {}
    for joint, (source, why) in structure.items():
        if joint in jmap.joints and joint not in chosen and source not in chosen.values():
            chosen[joint], guessed[joint] = source, why
    free = [n for n in names if n not in chosen.values()]
    scored = []  # (score, target joint, rig joint, the registered name it resembles)
    for joint in jmap.joints:
        if joint in chosen:
            continue
        for candidate in free:
            for known in called[joint]:
                if _side(known) == _side(candidate) and (a := _core(known)) and (b := _core(candidate)):
                    scored.append((difflib.SequenceMatcher(None, a, b).ratio(), joint, candidate, known))
    for score, joint, candidate, known in sorted(scored, key=lambda s: -s[0]):  # the best pairs first, each once
        if score >= SIMILAR and joint not in chosen and candidate not in chosen.values():
            chosen[joint], guessed[joint] = candidate, f"like {json.dumps(known)}"
    return chosen, guessed


def scaffold_joint_map(motion: RigMotion, target: str | None = None) -> tuple[str, dict[str, int]]:
    """A joint map to finish for a rig no registered map fits, started from the registered map (onto
    ``target``, or any) that leaves the fewest joints TODO (then: one the rig's names fit, most joints, most
    matched by name). Each target joint is written out with the rig's joint of the same name; else the one the rig's
    hierarchy and standing pose show (``omg.rig_structure``: SMPL-22 joints of a biped, SMAL-35 joints of a
    quadruped, whatever the names; the pose is the rest pose, or the rig's own frames where that stands on no
    legs; joints the map leaves to be filled in that the structure shows, a quadruped's neck and ears, are added);
    else the rig's joint whose name is closest to what the registered maps call it (same side, difflib
    ratio of the names' cores >= ``SIMILAR``); those two marked as a guess to check, with the reason;
    else ``TODO``. Returns the YAML text and the counts (matched, guessed, todo)."""
    import json

    from omg.rig_structure import Structure, rig_structure

    names = source_names(motion)
    maps = [m for m in registered_joint_maps() if target is None or m.target == target]
    if not maps:
        raise UsageError(f"no registered joint map targets {target!r}")
    called: dict[tuple[str, str], set[str]] = {}  # (skeleton, joint) -> what the registered maps call it
    for m in registered_joint_maps():
        for joint, source in m.joints.items():
            called.setdefault((m.target, joint), {joint}).add(source)
    shows = rig_structure(motion, _side) if any(m.target in ("smpl22", "smal35") for m in maps) else \
        Structure(None, {}, "")
    results = {}
    for m in maps:
        mine = {joint: called[(m.target, joint)] for joint in m.joints}
        results[m.name] = _scaffold(m, names, mine, shows.joints if m.target == shows.skeleton else {})

    def fewest_todo(m: JointMap) -> tuple:
        chosen, guessed = results[m.name]
        return len(m.joints) - len(chosen), bool(guessed), -len(m.joints), len(guessed) - len(chosen), m.name

    closest = min(maps, key=fewest_todo)
    chosen, guessed = results[closest.name]
    mine = shows.joints if closest.target == shows.skeleton else {}
    extra = [j for j in get_skeleton(closest.target).names if j in mine and j not in closest.joints
             and mine[j][0] not in chosen.values()]  # joints the map leaves to be filled in that the rig has
    chosen, guessed = {**chosen, **{j: mine[j][0] for j in extra}}, {**guessed, **{j: mine[j][1] for j in extra}}
    where = motion.source or motion.name
    counts = {"matched": len(chosen) - len(guessed), "guessed": len(guessed),
              "todo": len(closest.joints) - len(chosen) + len(extra)}
    width = max(map(len, [*closest.joints, *extra])) + 1
    kinds = {"smpl22": "standing biped", "smal35": "quadruped standing on four legs"}
    found = (f"# Its structure shows a {kinds[shows.skeleton]} ({shows.skeleton}) in {shows.pose}."
             if shows.skeleton else f"# Its structure shows no standing biped nor quadruped in {shows.pose}."
             if shows.pose else "")
    lines = [f"# A joint map of {where} onto {closest.target}, started from the registered map {closest.name!r}:",
             f"# {counts['matched']} joints matched by name, {counts['guessed']} guessed (check them), "
             f"{counts['todo']} {TODO} (write the rig's joint,",
             "# or delete the line: a joint between two mapped ones is filled in). Then pass it as --joint_map FILE.",
             *([found] if found else []),
             f"target: {closest.target}", f"category: {closest.category}",
             "joints:  # target joint: the rig's joint (<joint>_end: its end site)"]
    sided = any(j.startswith(("left_", "right_")) for j in mine)
    for joint in [*closest.joints, *extra]:
        key = f"{joint}:".ljust(width)
        if joint not in chosen:
            why = "" if closest.target not in kinds else \
                f", and its structure shows a {shows.skeleton} rig, no {kinds[closest.target]}" \
                if not mine and shows.skeleton else f", and its structure shows no {kinds[closest.target]}" \
                if not mine else ", and its pose does not tell left from right" \
                if joint.startswith(("left_", "right_")) and not sided else ", nor a joint there by its structure"
            lines.append(f"  {key} {TODO}  # {closest.name} maps it to {json.dumps(closest.joints[joint])}; "
                         f"the rig has no such joint{why}")
        elif joint in guessed:
            lines.append(f"  {key} {json.dumps(chosen[joint])}  # guessed: {guessed[joint]}; check")
        else:
            lines.append(f"  {key} {json.dumps(chosen[joint])}")
    return "\n".join(lines) + "\n", counts


@dataclass(frozen=True)
class _Plan:
    """How each target joint gets its place: source column, interpolation, or rigid follow."""

    source: dict  # target joint -> column in the source positions (mapped joints)
    between: dict  # target joint -> (joint a, joint b, fraction from a to b)
    proxied: tuple  # (J,) bool: mapped or interpolated


def _plan(target: Skeleton, jmap: JointMap, names: list[str]) -> _Plan:
    unknown = [t for t in jmap.joints if t not in target.names]
    if unknown:
        raise UsageError(f"joint map {jmap.name!r}: {', '.join(unknown)} are not joints of {target.name}")
    column = {n: i for i, n in enumerate(names)}
    source = {target.index(t): column[s] for t, s in jmap.joints.items()}
    lengths = target.bone_lengths()
    between = {}
    for chain in target.chains:
        cum = np.cumsum([0.0] + [lengths[j] for j in chain[1:]])  # template length along the chain
        mapped = [i for i, j in enumerate(chain) if j in source]
        for i, j in enumerate(chain[1:], start=1):
            if j in source:
                continue
            before = [k for k in mapped if k < i]
            after = [k for k in mapped if k > i]
            if before and after:
                a, b = before[-1], after[0]
                between[j] = (chain[a], chain[b], (cum[i] - cum[a]) / max(cum[b] - cum[a], 1e-9))
    proxied = tuple(j in source or j in between for j in range(target.num_joints))
    needed = {0} | {target.parents[e] for e in target.end_effectors}
    loose = [target.names[j] for j in sorted(needed) if not proxied[j]]
    if loose:
        raise UsageError(
            f"joint map {jmap.name!r} leaves {', '.join(loose)} of {target.name} unmapped; map them, or joints "
            "on both sides of them along their chain"
        )
    return _Plan(source, between, proxied)


def _proxy(plan: _Plan, target: Skeleton, src: torch.Tensor) -> torch.Tensor:
    """(T, S, 3) source positions -> (T, J, 3) target joint places (NaN where not proxied)."""
    out = torch.full((src.shape[0], target.num_joints, 3), float("nan"), dtype=src.dtype)
    for j, s in plan.source.items():
        out[:, j] = src[:, s]
    for j, (a, b, w) in plan.between.items():
        out[:, j] = out[:, a] + w * (out[:, b] - out[:, a])
    return out


def _up_rotation(q: torch.Tensor, target: Skeleton, up: str | None) -> torch.Tensor:
    """(4,) rotation turning the source's up axis to +Y.

    ``up`` ("y", "z", "-z", ...) names it. Detection: along the up axis the body's lowest
    joint stays on the floor, so its coordinate barely changes over the clip, while along a
    horizontal axis it follows the travel. +Y (the BVH and DeepMimic convention) is kept
    unless the lowest joint varies by over 5 cm along Y and another axis is twice as steady;
    the sign puts the body above its feet. Clips that neither travel nor stand (lying still)
    give no evidence and stay Y-up: pass ``up`` for Z-up files of that kind.
    """
    axes = {"x": 0, "y": 1, "z": 2}
    if up is not None:
        key = up.lower().lstrip("+-")
        if key not in axes:
            raise UsageError(f"up must be one of x, y, z (optionally signed), got {up!r}")
        k, sign = axes[key], -1.0 if up.startswith("-") else 1.0
    else:
        placed = [j for j in range(target.num_joints) if not torch.isnan(q[0, j, 0])]
        lowest = q[:, placed].min(1).values  # (T, 3)
        spread = torch.quantile(lowest, 0.75, dim=0) - torch.quantile(lowest, 0.25, dim=0)  # (3,)
        k = 1
        if spread[1] > 0.05:
            other = min((0, 2), key=lambda a: float(spread[a]))
            if spread[other] < 0.5 * spread[1]:
                k = other
        feet = [f for f in target.feet if f in placed]
        body = [j for j in placed if j not in feet]
        sign = 1.0
        if feet and body:
            sign = 1.0 if float((q[:, body, k].mean(1) - q[:, feet, k].mean(1)).median()) >= 0 else -1.0
    axis = torch.zeros(3, dtype=q.dtype)
    axis[k] = sign
    return quat_between(axis, torch.tensor([0.0, 1.0, 0.0], dtype=q.dtype))


def _floor(positions: torch.Tensor, skeleton: Skeleton, fps: float) -> float:
    """Height of the ground: the median height of the lowest foot joint in contact over the
    contact frames; the feet's 2nd percentile where no foot is ever in contact."""
    h = positions[:, list(skeleton.feet), 1]  # (T, F)
    contact = ground_contacts(positions, skeleton.feet, fps)
    lowest = torch.where(contact, h, torch.full_like(h, float("inf"))).min(1).values  # (T,)
    lowest = lowest[torch.isfinite(lowest)]
    return float(lowest.median()) if len(lowest) else float(torch.quantile(h.min(1).values, 0.02))


def retarget(
    motion: RigMotion,
    target: str | Skeleton = "smpl22",
    joint_map: str | Path | JointMap | None = None,
    fps: float | None = None,
    height: float | None = None,
    up: str | None = None,
    id: str | None = None,
    texts: Sequence[str] = (),
    **fields,
) -> Clip:
    """``motion`` on ``target`` as a clip with positions, local rotations and this individual's offsets.

    ``fps``: resample first (default: keep the source rate). ``height``: scale so that the
    rest pose's joints span this many metres vertically (SMPL template: 1.54). ``up``: the
    source's up axis ("y", "z", "-z", ...) where detection would fail. ``fields`` go to ``Clip``
    (labels, category, source).
    """
    skel = get_skeleton(target)
    jmap = resolve_joint_map(motion, skel, joint_map)
    names = source_names(motion)
    plan = _plan(skel, jmap, names)
    if fps is not None:
        motion = motion.resample(fps)
    if len(motion) < 2:
        where = motion.source or motion.name
        raise UsageError(f"{where}: {len(motion)} frame(s) at {motion.fps:g} fps, need 2 or more")
    J, parents = skel.num_joints, skel.parents
    tmpl = torch.from_numpy(skel.rest_offsets.astype(np.float64))  # (J, 3) template offsets
    tmpl_len = tmpl.norm(dim=-1)
    tmpl_dir = tmpl / tmpl_len.clamp_min(1e-9)[:, None]

    # bone lengths on the source's rest pose; joints without a place get the template's, scaled
    rest = _proxy(plan, skel, torch.from_numpy(motion.rest_positions(end_sites=True))[None])[0]  # (J, 3)
    measured = [j for j in range(1, J) if plan.proxied[j] and plan.proxied[parents[j]]]
    lengths = torch.zeros(J, dtype=torch.float64)
    for j in measured:
        lengths[j] = (rest[j] - rest[parents[j]]).norm()
    ratios = [float(lengths[j] / tmpl_len[j]) for j in measured if tmpl_len[j] > 1e-6]
    scale = float(np.median(ratios)) if ratios else 1.0
    for j in range(1, J):
        if j not in measured:
            lengths[j] = tmpl_len[j] * scale
    offsets = tmpl_dir * lengths[:, None]  # (J, 3) the individual's bones along the template's directions
    offsets[0] = tmpl[0] * scale

    q = _proxy(plan, skel, torch.from_numpy(motion.positions_with_end_sites()))  # (T, J, 3)
    T = q.shape[0]
    if not torch.isfinite(q[:, [j for j in range(J) if plan.proxied[j]]]).all():
        raise UsageError(f"{motion.source or motion.name}: non-finite joint positions")
    turn = _up_rotation(q, skel, up)
    q = quat_apply(turn.expand(T, J, 4), q)

    # rotations turning the template's directions onto the mapped ones, parents first
    local = positions_to_rotations(skel, q, offsets, placed=plan.proxied, aim_from_fk=False)
    positions = skel.forward_kinematics(local, q[:, 0], offsets=offsets)  # (T, J, 3)

    if height is not None:
        rest_pose = skel.forward_kinematics(quat_identity((1, J), torch.float64), offsets[0][None], offsets=offsets)
        factor = height / float(rest_pose[0, :, 1].max() - rest_pose[0, :, 1].min())
        positions, offsets = positions * factor, offsets * factor
    positions[..., 1] -= _floor(positions, skel, motion.fps)
    fields.setdefault("category", jmap.category)
    fields.setdefault("source", motion.source)
    return Clip(
        id=id or motion.name,
        skeleton=skel,
        fps=motion.fps,
        positions=positions.numpy().astype(np.float32),
        rotations=local.numpy().astype(np.float32),
        offsets=offsets.numpy().astype(np.float32),
        texts=list(texts),
        **fields,
    )


# ---------------------------------------------------------------------------------------------
# The other direction: a motion on a model skeleton written onto a user's rig.


def _rig_joint_map(rig: RigMotion, skel: Skeleton, joint_map: str | Path | JointMap | None) -> JointMap:
    """``resolve_joint_map``, but a rig whose names fit a map of another skeleton (a dog rig for a
    human motion) says so instead of listing the joints a human map misses."""
    if joint_map is None and detect_joint_map(rig, skel.name) is None:
        other = detect_joint_map(rig)
        if other is not None and other.target != skel.name:
            raise UsageError(
                f"{rig.source or rig.name}: the rig is a {other.category} rig (its names fit joint map "
                f"{other.name!r}, onto {other.target}), the motion is on {skel.name}: give a rig of the motion's kind"
            )
    return resolve_joint_map(rig, skel, joint_map)


def _leg_length(skel: Skeleton, positions: torch.Tensor) -> torch.Tensor:
    """(..., J, 3) -> (...,) length of the leg whose foot is nearest the root (SMPL's leg, SMAL's hind
    leg), from the hip joint down to the foot's top joint: the unit the root's path scales by."""
    def path(j: int) -> list[int]:
        out = [j]
        while skel.parents[out[-1]] > 0:
            out.append(skel.parents[out[-1]])
        return out

    tops = [f for f in skel.feet if skel.parents[f] not in skel.feet]
    leg = min((path(f) for f in tops), key=len)
    return sum((positions[..., a, :] - positions[..., b, :]).norm(dim=-1) for a, b in zip(leg[:-1], leg[1:]))


def _aims(rig: RigMotion, mapped: dict) -> list[list[int]]:
    """Per rig joint, the nearest mapped points below it (joints or end sites, columns of
    ``positions_with_end_sites``), found through unmapped joints, which stay rigid."""
    J = rig.num_joints
    children = [[c for c, p in enumerate(rig.parents) if p == j] for j in range(J)]
    ends = [[J + k for k, (p, _) in enumerate(rig.end_sites) if p == j] for j in range(J)]

    def below(j: int) -> list[int]:
        out = []
        for c in children[j] + ends[j]:
            out += [c] if c in mapped else (below(c) if c < J else [])
        return out

    return [below(j) for j in range(J)]


def _sampled(frames: int) -> np.ndarray:
    """At most ``FIT_FRAMES`` of a rig's own frames, evenly spread: what its means are taken over."""
    return np.unique(np.linspace(0, frames - 1, min(frames, FIT_FRAMES)).round().astype(int))


@dataclass(frozen=True)
class _Pose:
    """The rig's own pose that ``onto_rig`` turns its mapped joints from: the joints the model lacks as the rig
    holds them, the mapped ones at rest."""

    local: torch.Tensor  # (J, 4) local rotations
    world: torch.Tensor  # (J, 4) global rotations
    positions: torch.Tensor  # (J + E, 3) joints and end sites, the root at its offset


def _rig_pose(rig: RigMotion, mapped: dict) -> _Pose:
    """The pose the rig's joints the model lacks keep (``mapped``: rig joint -> model joint, those it has).

    A BVH rig's rest pose is a layout of bones, not a pose: the MANN dog's shoulders lie along its spine at
    rest and stand turned 80 and 127 degrees on every frame of its clip (spread 0.5 and 1.5 degrees), so its
    forelegs hung from them at rest stood 6-9 cm off. Such a joint keeps its mean rotation over the rig's own
    frames (the rotation nearest the mean of their matrices); a character's bind pose is its pose (its joints
    keep their rest)."""
    J = rig.num_joints
    local = quat_identity((J,), torch.float64)
    keep = [j for j in range(J) if j not in mapped]
    if rig.character is None and len(rig) and keep:
        held = torch.from_numpy(rig.rotations[_sampled(len(rig))][:, keep]).double()  # (t, K, 4)
        local[keep] = matrix_to_quat(nearest_rotation(quat_to_matrix(held).mean(0)))  # (K, 4)
    world = rig.skeleton().global_rotations(local[None])[0]
    translations = rig.offsets[None]
    positions = replace(rig, rotations=local[None].numpy(), translations=translations).positions_with_end_sites()[0]
    return _Pose(local, world, torch.from_numpy(positions))


def _solve_rig(rig: RigMotion, pose: _Pose, aims: list, model_of: dict, targets: torch.Tensor,
               frames: dict, fits: dict) -> tuple:
    """Local rotations (T, J, 4) and root translation (T, 3) of the rig turning each mapped joint's
    vectors to its aim points in the rig's own pose (``pose``) onto the target's vectors between the
    same model joints.

    ``targets``: (T, M, 3) model joint places in the rig's frame.
    A joint with one aim turns by the shortest arc from its direction in the rig's pose, in its parent's
    frame (its own orientation there is where it starts: an A-pose rig is not forced into a T-pose), one
    with several follows the model joint's own frame (``frames``: see ``_joint_frames``), else their best
    fit (Kabsch), turned by what the rig's own frames show that fit misses (``fits``: see ``_fit_turns``);
    unmapped joints keep their rotation in the rig's pose (``_rig_pose``).
    Returns the rotations, the top mapped joint (the pelvis) and its (T, 3) place.
    """
    T, J = targets.shape[0], rig.num_joints
    rest = pose.positions  # (J + E, 3)
    identity = quat_identity((T,), torch.float64)
    local = pose.local.expand(T, J, 4).clone()
    world = [identity] * J
    for j, p in enumerate(rig.parents):
        parent = world[p] if p >= 0 else identity
        kids = [c for c in aims[j] if float((rest[c] - rest[j]).norm()) > 1e-9] if j in model_of else []
        if kids:
            # (C, 3) the vectors in j's own frame (a mapped joint's own rotation in the pose is the identity; the
            # unmapped joints above it may turn it)
            v = quat_apply(quat_conjugate(pose.world[j]).expand(len(kids), 4), rest[kids] - rest[j])
            w = targets[:, [model_of[c] for c in kids]] - targets[:, model_of[j], None]  # (T, C, 3)
            if len(kids) == 1:
                aim = quat_apply(quat_conjugate(parent), w[:, 0])
                local[:, j] = quat_between(v[0].expand_as(aim), aim)
            elif j in frames:
                m, kids_m, dirs, at_rest = frames[j]
                now = kabsch(dirs, F.normalize(targets[:, kids_m] - targets[:, m, None], dim=-1))  # (T, 3, 3)
                local[:, j] = quat_mul(quat_conjugate(parent), matrix_to_quat(now @ at_rest))
            else:
                # directions weighted by the rig's bone lengths: a long bone (the spine) says more about
                # the joint's turn than a short stub (a tail root or hip joint sitting near the pelvis)
                best = kabsch(v, F.normalize(w, dim=-1) * v.norm(dim=-1, keepdim=True))  # (T, 3, 3)
                if j in fits:
                    best = best @ fits[j]
                local[:, j] = quat_mul(quat_conjugate(parent), matrix_to_quat(best))
        world[j] = quat_mul(parent, local[:, j])
    # the root goes where the top mapped joint (the pelvis) must be: the joints above it are rigid
    top = min(model_of)  # (joints added for aiming come after their mapped parent)
    return local, top, targets[:, model_of[top]]


def _fit_turns(rig: RigMotion, skel: Skeleton, jmap: JointMap, pose: _Pose, aims: list, model_of: dict,
               frames: dict, up: str | None) -> dict:
    """Per rig joint that ``_solve_rig`` turns by the best fit of its aims, the turn K that its own frames show
    the fit misses: rig = fit @ K, K nearest the mean of fit^T @ rig over the rig's own frames (at most
    ``FIT_FRAMES`` of them), the fit made on the model's places that the import (``retarget``) gives them.

    The model skeleton holds a joint's children where its template puts them, not where the rig has them: the
    MANN dog's forelegs hang from SMAL's withers (its Neck) along the template's directions, while the rig hangs
    them from its Spine1 through its shoulders, so the fit of Spine1's aims (its Neck and the two forelegs)
    tipped its chest and the forepaws stood 3.4-4.4 cm above the original on the way back. Where the rig's
    places are the model's (a rig on its own template, a character: none is measured), K is the identity."""
    todo = [j for j, kids in enumerate(aims) if j in model_of and j not in frames
            and len([c for c in kids if float((pose.positions[c] - pose.positions[j]).norm()) > 1e-9]) > 1]
    if rig.character is not None or len(rig) < 2 or not todo:
        return {}
    take = _sampled(len(rig))
    sample = replace(rig, rotations=rig.rotations[take], translations=rig.translations[take])
    plan = _plan(skel, jmap, source_names(rig))
    turn = _up_rotation(_proxy(plan, skel, torch.from_numpy(sample.positions_with_end_sites())), skel, up)
    model = torch.from_numpy(retarget(sample, skel, jmap, up=up).positions).double()  # (t, M, 3) Y up
    model = quat_apply(quat_conjugate(turn).expand(*model.shape[:2], 4), model)  # the rig's frame, as ``retarget``'s
    held = sample.skeleton().global_rotations(torch.from_numpy(sample.rotations).double())  # (t, J, 4)
    fits = {}
    for j in todo:
        kids = [c for c in aims[j] if float((pose.positions[c] - pose.positions[j]).norm()) > 1e-9]
        v = quat_apply(quat_conjugate(pose.world[j]).expand(len(kids), 4), pose.positions[kids] - pose.positions[j])
        w = model[:, [model_of[c] for c in kids]] - model[:, model_of[j], None]  # (t, C, 3)
        fit = kabsch(v, F.normalize(w, dim=-1) * v.norm(dim=-1, keepdim=True))  # (t, 3, 3)
        mean = (fit.transpose(-1, -2) @ quat_to_matrix(held[:, j])).mean(0)  # (3, 3)
        fits[j] = nearest_rotation(mean)
    return fits


def _joint_frames(rig: RigMotion, skel: Skeleton, plan: _Plan, pose: _Pose, aims: list,
                  model_of: dict, own: torch.Tensor) -> dict:
    """Per rig joint with several aims (a pelvis, a chest), how its model joint's frame maps onto it.

    A model joint's frame is the best fit of the template's directions to its child bones (as on import).
    The rig's joint is rigid with that frame: rig = model @ C in every frame. This keeps the rig's hip and
    tail stubs where the rig has them, where a fit of the model's stubs (template directions on import) would
    tilt the pelvis. A BVH rig's own frames give C: the rotation nearest the mean of model^T @ rig over them
    (the model frame measured on the rig's mapped places, as on import). Its rest pose is a layout of bones, not
    a pose: the MANN dog's Hips and Spine lie along one line at rest, while its clip turns the Spine 133
    degrees on the Hips, so C from its rest (the model frame there R0, the rig's the identity: C = R0^T) turned
    its Hips 50-70 degrees and its hips stood 7 cm off the ground. A character's bind pose is its pose:
    C = R0^T @ W, R0 the model frame in ``pose``, W the rig joint's there.
    """
    lengths = np.linalg.norm(skel.rest_offsets, axis=-1)
    rest_model = _proxy(plan, skel, pose.positions[None])[0]
    clip = turns = None
    if rig.character is None and len(rig):
        take = _sampled(len(rig))
        clip = _proxy(plan, skel, own[take])  # (t, J, 3)
        turns = rig.skeleton().global_rotations(torch.from_numpy(rig.rotations[take]).double())  # (t, J, 4)
    frames = {}
    for r, kids in enumerate(aims):
        # only where every aim hangs right below the joint: a joint the map skips may carry the rig's own
        # turn (the MANN dog's Spine sits on its Hips and turns the back), and then the joint's frame is not
        # the model's; the best fit of the directions (``_solve_rig``) serves those
        if r not in model_of or len(kids) < 2 or any(_parent_of(rig, c) != r for c in kids):
            continue
        m = model_of[r]
        kids_m = [c for c in skel.children(m) if plan.proxied[c] and lengths[c] > 1e-9]
        if len(kids_m) < 2:
            continue
        dirs = F.normalize(torch.from_numpy(skel.rest_offsets[kids_m].astype(np.float64)), dim=-1)
        observed = F.normalize(rest_model[kids_m] - rest_model[m], dim=-1)
        if not torch.isfinite(observed).all():
            continue
        if clip is not None:
            # rig = model @ C, C nearest the mean of model^T @ rig over the rig's own frames
            seen = F.normalize(clip[:, kids_m] - clip[:, m, None], dim=-1)  # (T, K, 3)
            held = (kabsch(dirs, seen).transpose(-1, -2) @ quat_to_matrix(turns[:, r])).mean(0)  # (3, 3)
            frames[r] = (m, kids_m, dirs, nearest_rotation(held))
        else:
            # rig = model @ R0^T @ W, W the rig joint's own frame in the pose
            frames[r] = (m, kids_m, dirs, kabsch(dirs, observed).transpose(-1, -2) @ quat_to_matrix(pose.world[r]))
    return frames


def _parent_of(rig: RigMotion, column: int) -> int:
    """The parent joint of a rig column: a joint's, or an end site's."""
    return rig.parents[column] if column < rig.num_joints else rig.end_sites[column - rig.num_joints][0]


def _foot_points(rig: RigMotion, feet: list[int]) -> list[int]:
    """Columns of ``positions_with_end_sites``: the rig's mapped foot joints, every joint below them (toes,
    a toe's end joint) and their end sites: what stands on the ground."""
    below = set(feet)
    for j, p in enumerate(rig.parents):  # parents come first
        if p in below:
            below.add(j)
    return sorted(below) + [rig.num_joints + k for k, (p, _) in enumerate(rig.end_sites) if p in below]


@dataclass(frozen=True)
class _Foot:
    """One foot of the model (SMPL's ankle and toe, SMAL's paw) on the rig: what of the rig stands on the ground."""

    group: int  # its group in ``omg.io.contacts.foot_groups``
    points: list[int]  # columns of ``positions_with_end_sites``: the rig's foot joints, those below, their end sites
    carriers: list[int]  # a character's sole: the joint each of its mesh points follows
    offsets: torch.Tensor  # (K, 3) each mesh point from its joint at rest
    raised: torch.Tensor  # (P + K,) each point's height at rest above the mesh's sole (0 on a rig without a stance)


def _feet(rig: RigMotion, skel: Skeleton, plan: _Plan, up_axis: torch.Tensor) -> list[_Foot]:
    """The rig's feet, one per group of the model's foot joints (``omg.io.contacts.foot_groups``) it maps.

    A character (glTF, FBX: its bind pose stands on its mesh's sole) stands on its mesh: the foot's joints, those
    below and their end sites, and the skinned mesh's low vertices that follow them (``Character.ground``: the
    heel behind the ankle, the toes past the last joint), each raised by its height above the sole at rest, so
    that a foot rolling onto its heel or its toes touches the ground with whichever is lowest, as a shoe does.
    A BVH rig's rest pose is a layout of bones, not a stance: its foot points stand on the ground as they are."""
    from omg.io.contacts import foot_groups

    rest = torch.from_numpy(rig.rest_positions(end_sites=True))
    sole = rig.sole
    ground = getattr(rig.character, "ground", None) if sole is not None else None
    feet = []
    for g, group in enumerate(foot_groups(skel)):
        mapped = [plan.source[f] for f in group if f in plan.source]
        if not mapped:
            continue
        points = _foot_points(rig, mapped)
        joints = [p for p in points if p < rig.num_joints]
        carriers, offsets = [], torch.zeros(0, 3, dtype=torch.float64)
        if ground is not None:
            mine = np.isin(ground[1], joints)
            carriers = ground[1][mine].tolist()
            offsets = torch.from_numpy(ground[0][mine]) - rest[carriers]
        if sole is None:
            raised = torch.zeros(len(points) + len(carriers), dtype=torch.float64)
        else:
            raised = torch.cat([rest[points], rest[carriers] + offsets]) @ up_axis - sole
        feet.append(_Foot(g, points, carriers, offsets, raised))
    return feet


def _foot_levels(motion: RigMotion, feet: list[_Foot], up_axis: torch.Tensor) -> torch.Tensor:
    """(T, F) the level of each foot's sole along ``up_axis``: the lowest of its points less its height at rest
    above the sole (``_feet``); on a rig without a stance, its lowest point."""
    x = torch.from_numpy(motion.positions_with_end_sites())  # (T, S, 3)
    turns = None
    levels = []
    for foot in feet:
        heights = x[:, foot.points] @ up_axis  # (T, P)
        if foot.carriers:
            if turns is None:  # (T, J, 4): rest rotations are the identity
                turns = motion.skeleton().global_rotations(torch.from_numpy(motion.rotations))
            c = foot.carriers
            mesh = x[:, c] + quat_apply(turns[:, c], foot.offsets.expand(len(x), -1, -1))  # (T, K, 3)
            heights = torch.cat([heights, mesh @ up_axis], 1)
        levels.append((heights - foot.raised).min(1).values)
    return torch.stack(levels, 1)


def _own_height(rig: RigMotion, frames: torch.Tensor, points: list[int], up_axis: torch.Tensor,
                leg: float) -> float | None:
    """Metres the lowest of ``points`` (a foot's, or all feet's) stands above the ground when planted on a BVH
    rig's own clip: its median height over the clip's frames where they are planted; None on a rig without
    a clip (or a character: its feet stand on its mesh's sole, ``_feet``), or where it is over a tenth of the
    leg or under the floor (no foot's). ``frames``: (T, J + E, 3) the rig's ``positions_with_end_sites``."""
    if rig.sole is not None or len(rig) <= 2:
        return None
    at = frames[:, points] @ up_axis  # (T, P) heights
    yup = torch.zeros(len(rig), len(points), 3, dtype=torch.float64)
    yup[..., 1] = at
    # the horizontal distance: enough for the speed
    yup[..., 0] = (frames[:, points] - at[..., None] * up_axis).norm(dim=-1)
    planted = ground_contacts(yup, list(range(len(points))), rig.fps).any(1)
    height = float(at.min(1).values[planted].median()) if planted.any() else 0.0
    return height if 0.0 <= height <= 0.1 * leg else None


def _clearance(rig: RigMotion, frames: torch.Tensor, points: list[int], up_axis: torch.Tensor, leg: float) -> float:
    """Metres the rig's lowest foot point stands above its ground when planted: on a BVH rig with a clip its
    height on its own planted frames (``_own_height``: joints sit inside the foot, Bandai's toe ends stand 4 cm
    up), else 0 (a character's feet stand on its mesh's sole: ``_feet``)."""
    height = _own_height(rig, frames, points, up_axis, leg)
    return 0.0 if height is None else height


def _slope(d: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (...,) radians a direction points down from the horizontal plane of ``up``."""
    return torch.asin((-(d @ up) / d.norm(dim=-1).clamp_min(1e-12)).clamp(-1.0, 1.0))


def _stance_pitches(rig: RigMotion, skel: Skeleton, plan: _Plan, pos: torch.Tensor, contact: torch.Tensor,
                    up_axis: torch.Tensor) -> dict[tuple[int, int], float]:
    """Per foot of a character, (ankle, toe) model joints -> radians its foot must pitch down more than the
    model's: the character's slope of that bone at rest less the model's on its flat-footed frames (both
    joints planted in ``contact``, (T, F) over ``skel.feet``; the template's without one).

    A character's bind pose stands on its soles, so its foot bone's slope at rest is its flat foot's: where the
    model's foot is flat the character's is, whichever way the two skeletons place ankle and toe on the foot
    (a figure whose toe joint sits under its ankle has a steep bone, the model's a shallow one, and the same
    direction would tip its sole 40 degrees). A BVH rig's rest pose is a layout of bones, not a stance: its
    feet follow the model's bones as its other limbs do (a clip's round trip comes back as it went)."""
    from omg.io.contacts import foot_groups

    if rig.sole is None:
        return {}
    rest = torch.from_numpy(rig.rest_positions(end_sites=True))
    feet = list(skel.feet)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    out = {}
    for group in foot_groups(skel):
        if len(group) < 2 or any(j not in plan.source for j in group[:2]):
            continue
        ankle, toe = group[:2]
        flat = contact[:, [feet.index(ankle), feet.index(toe)]].all(1)
        model = _slope(pos[:, toe] - pos[:, ankle], up)  # (T,)
        template = _slope(torch.from_numpy(skel.rest_offsets[toe].astype(np.float64)), up)
        character = _slope(rest[plan.source[toe]] - rest[plan.source[ankle]], up_axis)
        out[(ankle, toe)] = float(character - (model[flat].median() if flat.any() else template))
    return out


def _pitched(targets: torch.Tensor, pitches: dict[tuple[int, int], float]) -> torch.Tensor:
    """(T, J, 3) Y-up model joint places with each foot's toe turned about its ankle, in the vertical plane of
    the bone, down by its pitch (``_stance_pitches``); the bone keeps its length and heading."""
    if not pitches:
        return targets
    out = targets.clone()
    for (ankle, toe), pitch in pitches.items():
        d = targets[:, toe] - targets[:, ankle]  # (T, 3)
        flat = d * torch.tensor([1.0, 0.0, 1.0], dtype=d.dtype)
        heading = F.normalize(flat, dim=-1)
        slope = torch.atan2(-d[:, 1], flat.norm(dim=-1)) + pitch
        turned = d.norm(dim=-1, keepdim=True) * (torch.cos(slope)[:, None] * heading
                                                 - torch.sin(slope)[:, None] * torch.tensor([0.0, 1.0, 0.0]))
        vertical = flat.norm(dim=-1) < 1e-9  # a foot pointing straight down has no heading: it stays
        out[:, toe] = torch.where(vertical[:, None], targets[:, toe], targets[:, ankle] + turned)
    return out


def onto_rig(
    positions: np.ndarray,  # (T, J, 3) metres, Y up, on ``skeleton``
    skeleton: Skeleton | str,
    rig: RigMotion,
    fps: float,
    joint_map: str | Path | JointMap | None = None,
    up: str | None = None,
    clean_contacts: bool = True,
) -> RigMotion:
    """A motion of a model skeleton on a user's rig (read with ``read_rig``: a BVH file, a glTF or FBX character):
    the rig's hierarchy, names, channels, unit, rest pose and bone lengths (and character), its animation
    replaced.

    The joint map is the import's, used the other way (detected from the rig's names, or given).
    Each mapped rig joint turns so that its bones towards the next mapped joints below it follow
    the model's bones between the same joints; joints the model lacks (fingers, twist bones, extra
    spine joints, a dog's shoulders) keep the rotation relative to their parent that the rig holds them in: a
    BVH rig's mean over its own frames (its rest pose is a layout of bones), a character's bind pose
    (``_rig_pose``); a joint that follows its model joint's frame keeps the relation the rig's own frames
    show (``_joint_frames``). The root travels the model's
    path scaled by the ratio of the rig's leg length to the model's, in the rig's up axis (detected
    from its own frames as on import; ``up`` names it), on the rig's ground: where the model's feet are
    planted the rig's lowest foot point stands at the rig's own clearance. With ``clean_contacts`` feet
    planted on the rig stay where they landed (``omg.io.contacts``), its legs re-aimed at the pinned places;
    a character's planted feet are also put with their soles on the floor on each frame, and its feet in the
    air kept above it; a BVH rig's planted feet each stand, over their contacts, within ``FOOT_TOLERANCE`` of
    the height that foot has on the rig's own planted frames. A character's foot bones keep their own slope at
    stance (``_stance_pitches``).
    """
    from omg.io.contacts import clean_foot_contacts, foot_groups

    skel = get_skeleton(skeleton)
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64)
    if pos.ndim != 3 or pos.shape[1:] != (skel.num_joints, 3) or len(pos) < 1:
        raise UsageError(f"motion must be (T, {skel.num_joints}, 3) joint positions on {skel.name}, "
                         f"got {tuple(pos.shape)}")  # fmt: skip
    where = rig.source or rig.name
    jmap = _rig_joint_map(rig, skel, joint_map)
    names = source_names(rig)
    plan = _plan(skel, jmap, names)
    rest = torch.from_numpy(rig.rest_positions(end_sites=True))  # (J + E, 3) rig frame
    rig_leg = float(_leg_length(skel, _proxy(plan, skel, rest[None])[0]))
    if not rig_leg > 1e-6:
        raise UsageError(f"{where}: the rig has no rest pose (its leg joints' OFFSETs are zero); "
                         "give a BVH whose hierarchy holds the rig's bones")  # fmt: skip
    own = torch.from_numpy(rig.positions_with_end_sites())  # (T, J + E, 3) the rig's own frames
    turn = _up_rotation(_proxy(plan, skel, own), skel, up)
    back = quat_conjugate(turn)  # Y up -> the rig's frame
    scale = rig_leg / float(_leg_length(skel, pos).mean().clamp_min(1e-6))
    model_of = {column: j for j, column in plan.source.items()}  # rig column -> model joint
    # a joint the map skips that sits on its mapped parent (the MANN dog's Spine on its Hips) turns
    # with that parent's model joint: it carries the rig's bend towards the next mapped joint, while the
    # parent turns with the mapped bones right below it, where it has two or more (the dog's legs and
    # tail; CMU's Hips has none: its hip and back joints sitting on it keep aiming through)
    aim_of = dict(model_of)
    direct = {p: 0 for p in model_of}
    for c in model_of:
        if c > 0 and _parent_of(rig, c) in direct and float((rest[c] - rest[_parent_of(rig, c)]).norm()) > 1e-9:
            direct[_parent_of(rig, c)] += 1
    for u, p in enumerate(rig.parents):
        if u not in aim_of and direct.get(p, 0) >= 2 and np.linalg.norm(rig.offsets[u]) < 1e-9:
            aim_of[u] = aim_of[p]
    aims = _aims(rig, aim_of)
    pose = _rig_pose(rig, aim_of)
    rest = pose.positions
    frames = _joint_frames(rig, skel, plan, pose, aims, aim_of, own)
    fits = _fit_turns(rig, skel, jmap, pose, aims, aim_of, frames, up)
    T = len(pos)
    up_axis = quat_apply(back, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))  # (3,) in the rig's frame

    def solve(targets_yup: torch.Tensor) -> tuple:
        targets = quat_apply(back.expand(T, skel.num_joints, 4), targets_yup)
        return _solve_rig(rig, pose, aims, aim_of, targets, frames, fits)

    def placed(local: torch.Tensor, top: int, at: torch.Tensor) -> RigMotion:
        # the joints above the pelvis are unmapped, so rigid in the rig's pose: the pelvis's own position
        # channels carry the path where it has them (Bandai's static joint_Root stays put), else the root's
        translations = np.broadcast_to(rig.offsets, (T, rig.num_joints, 3)).copy()
        own = top > 0 and any(c.endswith("position") for c in (rig.channels or [()] * rig.num_joints)[top])
        if own:
            above = rig.parents[top]
            translations[:, top] = quat_apply(quat_conjugate(pose.world[above]).expand(T, 4), at - rest[above]).numpy()
        else:
            translations[:, 0] = (at - (rest[top] - rest[0])).numpy()
        return replace(rig, fps=float(fps), rotations=local.numpy(), translations=translations)

    # (T, F) the model's planted feet; a single frame is a stance, but no flat foot to measure a slope on
    planted = ground_contacts(pos, skel.feet, float(fps)) if T > 1 else torch.zeros(T, len(skel.feet)) > 0
    local, top, at = solve(_pitched(pos * scale, _stance_pitches(rig, skel, plan, pos, planted, up_axis)))
    # the ground: in the frames where the model's feet are planted, the rig's lowest foot stands at its own
    # clearance, on the floor of the rig's frame (its up axis): a character's sole (its mesh, ``_feet``), a BVH
    # rig's lowest foot point as high as on its own planted frames; the scaled path alone leaves the feet where
    # the model's ankle height, scaled, puts them, off the rig's by the difference of the two
    feet = _feet(rig, skel, plan, up_axis)
    lowest = _foot_levels(placed(local, top, at), feet, up_axis).min(1).values  # (T,)
    contact = planted.any(1) if T > 1 else torch.ones(T, dtype=torch.bool)
    stance = rig.sole is not None and clean_contacts and T > 1
    if not contact.any():
        ground = torch.quantile(lowest, 0.02)
    elif stance:  # its planted feet go onto the sole below: a leg bends up to any, but may not stretch down
        ground = torch.quantile(lowest[contact], STANCE_GROUND)
    else:
        ground = lowest[contact].median()
    clearance = _clearance(rig, own, sorted({p for f in feet for p in f.points}), up_axis, rig_leg)
    out = placed(local, top, at - (ground - clearance) * up_axis)
    if clean_contacts and T > 1:
        # the rig's own places of the model joints, Y up: its feet are what must stay planted
        on_rig = _proxy(plan, skel, torch.from_numpy(out.positions_with_end_sites()))
        on_rig = quat_apply(turn.expand(T, skel.num_joints, 4), on_rig)
        filled = torch.where(torch.isnan(on_rig), on_rig[:, :1].expand_as(on_rig), on_rig)
        # a character's planted foot on its sole, frame by frame: one ground for the clip leaves its roll from heel
        # to toes (the model's foot is not the character's) a centimetre or more off; the clean-up carries the
        # rise with its pin, and the leg bends or stretches to it. A BVH rig's feet go as the model's: its clip
        # comes back as it went
        rise = None
        heights = [None] * len(feet) if stance else [_own_height(rig, own, f.points, up_axis, rig_leg) for f in feet]
        if stance:
            rise = np.zeros((T, len(foot_groups(skel))))  # (T, G) a foot the rig lacks stays where it is
            rise[:, [f.group for f in feet]] = (clearance - _foot_levels(out, feet, up_axis)).numpy()
        elif any(height is not None for height in heights):
            # a BVH rig's planted foot stands, over its contacts, within FOOT_TOLERANCE of the height that foot
            # has on the rig's own planted frames (the median of each; the least move): one ground for all feet
            # leaves a foot whose joints sit higher or lower in it than the lowest foot's off by the difference
            # (the DeepMimic dog's feet 1.2-1.5 cm, the MANN dog's forepaws); its motion within them stays the
            # model's
            rise = np.zeros((T, len(foot_groups(skel))))
            held = ground_contacts(filled, skel.feet, float(fps), max_speed=GROUND_CONTACT_SPEED)  # the clean-up's
            levels = _foot_levels(out, feet, up_axis)  # (T, F)
            for k, (foot, height) in enumerate(zip(feet, heights)):
                here = held[:, [list(skel.feet).index(j) for j in foot_groups(skel)[foot.group]]].any(1)
                if height is not None and here.any():
                    off = height - float(levels[here, k].median())
                    off = float(np.sign(off)) * max(abs(off) - FOOT_TOLERANCE, 0.0)
                    rise[here.numpy(), foot.group] = off
        # retargeting's contact rule (slow and low), not the clean-up's looser one for generated feet: a
        # slowly walking dog's feet are not planted
        cleaned = clean_foot_contacts(filled.numpy(), skel, float(fps), max_speed=GROUND_CONTACT_SPEED, rise=rise)
        cleaned = torch.from_numpy(cleaned).double()
        out = placed(*solve(torch.where(torch.isnan(on_rig), on_rig, cleaned)))
    return out


def rig_round_trip(rig: RigMotion, skeleton: str | Skeleton, joint_map: str | Path | JointMap | None = None) -> dict:
    """How well a rig's own clip survives import onto ``skeleton`` and export back onto the rig.

    Errors compare every joint and end site of the rig (the ones the model lacks included) after
    one constant translation (the import puts the floor at y = 0): ``mean_cm`` and ``max_cm``;
    ``mapped_mean_cm`` over the joints the map names; ``bone_cm``: the largest change of a bone's
    length in any frame; ``slide_*_cm_s``: the mean speed of the mapped foot points over the frames
    where the model's feet are planted (``ground_contacts``), in the original and on the way back;
    ``ground_cm``, ``ground_p95_cm``, ``ground_max_cm``: over those frames, how far the rig's lowest foot
    point (its feet, toes and their end sites, along its up axis, no translation removed) is on the way
    back from where the original has it: the median, 95th percentile and largest; ``foot_cm``, ``foot_p95_cm``:
    the same for each foot of the model on its own (its rig joints, those below and their end sites, over the
    frames where that foot is planted), the largest median and the largest 95th percentile of the feet.
    """
    skel = get_skeleton(skeleton)
    jmap = _rig_joint_map(rig, skel, joint_map)
    clip = retarget(rig, skel, jmap)
    back = onto_rig(clip.positions, skel, rig, clip.fps, jmap)
    a, b = rig.positions_with_end_sites(), back.positions_with_end_sites()  # (T, S, 3)
    d = b - a
    err = np.linalg.norm(d - d.reshape(-1, 3).mean(0), axis=-1) * 100  # (T, S) cm
    plan = _plan(skel, jmap, source_names(rig))
    mapped = sorted(plan.source.values())
    parents = np.array(rig.parents[1:] + [p for p, _ in rig.end_sites])
    child = np.arange(1, a.shape[1])

    def lengths(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(x[:, child] - x[:, parents], axis=-1)

    contact = ground_contacts(torch.from_numpy(clip.positions).double(), skel.feet, clip.fps).numpy()  # (T, F)
    planted = contact[:-1] & contact[1:]  # (T - 1, F)
    feet = [plan.source[f] for f in skel.feet]
    # the lowest foot point of the rig on the way back, over the frames with a planted foot, from the ground
    turn = _up_rotation(_proxy(plan, skel, torch.from_numpy(a)), skel, None)
    up_axis = quat_apply(quat_conjugate(turn), torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)).numpy()
    points = _foot_points(rig, feet)
    heights = [(x[:, points] @ up_axis).min(1) for x in (a, b)]  # (T,) the lowest foot point, original and back
    off_ground = np.abs(heights[1] - heights[0])[contact.any(1)] * 100  # (planted frames,) cm
    # each foot on its own, over the frames where the model's foot is planted: the lowest point of all of them
    # hides a foot standing above the others (the MANN dog's forepaws, while its hind paws are the lowest)
    from omg.io.contacts import foot_groups

    per_foot = []  # (median, 95th percentile) cm per foot of the model the rig has
    for group in foot_groups(skel):
        at = _foot_points(rig, [plan.source[f] for f in group])
        here = contact[:, [list(skel.feet).index(f) for f in group]].any(1)
        if here.any():
            off = np.abs((b[:, at] @ up_axis).min(1) - (a[:, at] @ up_axis).min(1))[here] * 100
            per_foot.append((float(np.median(off)), float(np.percentile(off, 95))))

    def slide(x: np.ndarray) -> float:
        speed = np.linalg.norm(np.diff(x[:, feet], axis=0), axis=-1) * clip.fps * 100  # (T - 1, F) cm/s
        return float(speed[planted].mean()) if planted.any() else 0.0

    return {
        "rig": rig.name, "map": jmap.name, "frames": len(rig), "joints": rig.num_joints,
        "mapped": len(mapped), "mean_cm": float(err.mean()), "max_cm": float(err.max()),
        "mapped_mean_cm": float(err[:, mapped].mean()),
        "bone_cm": float(np.abs(lengths(b) - lengths(a)).max() * 100),
        "slide_original_cm_s": slide(a), "slide_back_cm_s": slide(b),
        "ground_cm": float(np.median(off_ground)) if len(off_ground) else 0.0,
        "ground_p95_cm": float(np.percentile(off_ground, 95)) if len(off_ground) else 0.0,
        "ground_max_cm": float(off_ground.max(initial=0.0)),
        "foot_cm": max((m for m, _ in per_foot), default=0.0),
        "foot_p95_cm": max((p for _, p in per_foot), default=0.0),
    }  # fmt: skip


RIG_SUFFIXES = (".bvh", ".glb", ".gltf", ".fbx")


def read_rig_file(path: str | Path, what: str = "--to_rig") -> RigMotion:
    """A user's rig: a BVH file's hierarchy, a skinned glTF character (``omg.io.gltf.read_character``,
    which the glTF writer animates whole) or an FBX character (``omg.io.fbx.read_character``, read and
    written by Blender); a regular file of bounded size (no FIFO or /dev/zero)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".bvh":
        from omg.io.bvh import read_bvh

        return read_bvh(path, what=what)
    if suffix in (".glb", ".gltf"):
        from omg.io.gltf import read_character

        return read_character(path, what=what)
    if suffix == ".fbx":
        from omg.io.fbx import read_character as read_fbx

        return read_fbx(path, what=what)
    raise UsageError(f"{what} {path}: the rig must be a .bvh file (its HIERARCHY is the rig), a skinned glTF "
                     "character (.glb, .gltf) or an FBX character (.fbx)")


def read_rig(path: str | Path, skeleton: str | Skeleton, joint_map: str | Path | JointMap | None = None) -> RigMotion:
    """The rig of a BVH file or a glTF or FBX character for ``onto_rig``, checked against ``skeleton`` before any
    work is done: a rig no map fits, one of the other kind (a dog rig for a human motion) or one without
    a rest pose is one UsageError."""
    rig = read_rig_file(path)
    skel = get_skeleton(skeleton)
    plan = _plan(skel, _rig_joint_map(rig, skel, joint_map), source_names(rig))
    rest = torch.from_numpy(rig.rest_positions(end_sites=True))
    if not float(_leg_length(skel, _proxy(plan, skel, rest[None])[0])) > 1e-6:
        why = "its leg joints' OFFSETs are zero" if rig.character is None else "its leg joints stand on one point"
        raise UsageError(f"{path}: the rig has no rest pose ({why}); give a rig whose hierarchy holds its bones")
    return rig
