"""DeepMimic motion files (JSON ``{"Loop": ..., "Frames": [[...], ...]}``) with their character file.

The character file (``char_*.txt``, JSON) lists ``Skeleton.Joints`` in order, each with
``Name``, ``Type``, ``Parent`` and its attachment ``AttachX/Y/Z`` in the parent's frame.
A motion frame is ``[duration, root position (3), root rotation (w, x, y, z), then per
non-root joint in the character's order: spherical -> quaternion (w, x, y, z),
revolute -> one angle in radians about the joint's Z axis, fixed/none -> nothing]``.
Units are metres, +Y up (characters face +X). A joint's rotation turns its children's
attachments, as in BVH, so the motion maps onto ``RigMotion`` directly. The root's own
attachment is ignored (the frames hold its position).

Joints without child joints get an end site from their body (``BodyDefs``) so that joint maps
can reach toe tips, the head and the tail tip (named ``<joint>_end`` in maps): a sphere's
centre, or twice the attachment of a box or capsule, whose centre lies mid-segment.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES, read_file, read_head
from omg.io.rig import RigMotion, sample_frames
from omg.rotations import quat_normalize

DOFS = {"spherical": 4, "revolute": 1, "fixed": 0, "none": 0}


class DeepMimicError(UsageError):
    """A malformed DeepMimic motion or character file; the message names the file and the reason."""


def _load_json(path: Path, what: str = "") -> dict:
    try:
        data = json.loads(read_file(path, what, MOTION_MAX_BYTES).decode("utf-8", errors="replace"))
    except json.JSONDecodeError as e:
        raise DeepMimicError(f"{path}: not valid JSON ({e.msg} at line {e.lineno}; truncated file?)") from None
    if not isinstance(data, dict):
        raise DeepMimicError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def is_deepmimic_motion(path: str | Path) -> bool:
    """Whether a .txt/.json file looks like a DeepMimic motion: a JSON object with "Frames".

    Only the start of the file is read; a truncated motion still counts (and fails to read).
    """
    try:
        head = read_head(path, 4096).decode("utf-8", errors="replace")
    except UsageError:  # no file to read (a FIFO would block an open)
        return False
    return head.lstrip().startswith("{") and '"Frames"' in head


def find_character(motion_path: str | Path) -> Path:
    """The character file beside a motion: the only ``char_*.txt`` there, or the one whose
    name matches the motion's prefix (``humanoid3d_walk.txt`` -> ``char_humanoid3d.txt``)."""
    motion_path = Path(motion_path)
    candidates = sorted(motion_path.parent.glob("char_*.txt"))
    if len(candidates) == 1:
        return candidates[0]
    prefix = motion_path.stem.split("_")[0]
    named = [c for c in candidates if c.stem == f"char_{prefix}"]
    if len(named) == 1:
        return named[0]
    found = ", ".join(c.name for c in candidates) or "none"
    raise DeepMimicError(
        f"{motion_path}: cannot tell which character file describes it (char_*.txt beside it: {found}); "
        "pass character=PATH (the manifest's skeleton_file)"
    )


def read_character(path: str | Path) -> tuple[list[str], list[int], np.ndarray, list[str], list]:
    """(names, parents, (J, 3) attachments in metres, joint types, end sites) from a character file."""
    path = Path(path)
    data = _load_json(path)
    joints = data.get("Skeleton", {}).get("Joints") if isinstance(data.get("Skeleton"), dict) else None
    if not isinstance(joints, list) or not joints:
        raise DeepMimicError(f"{path}: not a DeepMimic character file (no Skeleton.Joints list)")
    names, parents, offsets, types = [], [], [], []
    for j, joint in enumerate(joints):
        try:
            name, kind, parent = str(joint["Name"]), str(joint["Type"]).lower(), int(joint["Parent"])
            attach = [float(joint.get(f"Attach{a}", 0.0)) for a in "XYZ"]
            theta = [float(joint.get(f"AttachTheta{a}", 0.0)) for a in "XYZ"]
        except (KeyError, TypeError, ValueError) as e:
            raise DeepMimicError(f"{path}: joint {j} lacks or garbles {e} "
                                 "(needs Name, Type, Parent, AttachX/Y/Z)") from None
        if kind not in DOFS:
            raise DeepMimicError(f"{path}: joint {name!r} has type {kind!r}; supported: {', '.join(DOFS)}")
        if (j == 0) != (parent == -1) or parent >= j:
            raise DeepMimicError(f"{path}: joint {name!r} has parent {parent}; "
                                 "joints must follow their parents, root first")
        if any(abs(t) > 1e-9 for t in theta):
            raise DeepMimicError(f"{path}: joint {name!r} has a rotated attachment (AttachTheta), "
                                 "which is not supported")
        names.append(name)
        parents.append(parent)
        offsets.append([0.0, 0.0, 0.0] if j == 0 else attach)
        types.append(kind)
    end_sites = []
    bodies = {str(b.get("Name")): b for b in data.get("BodyDefs", []) if isinstance(b, dict)}
    for j, name in enumerate(names):
        body = bodies.get(name)
        if j in parents or body is None or body.get("Shape") not in ("sphere", "box", "capsule"):
            continue
        try:
            centre = np.array([float(body.get(f"Attach{a}", 0.0)) for a in "XYZ"])
        except (TypeError, ValueError):
            continue  # a body without a usable attachment gives no end site
        end = centre if body["Shape"] == "sphere" else 2.0 * centre
        if np.linalg.norm(end) > 1e-6:
            end_sites.append((j, end))
    return names, parents, np.asarray(offsets, dtype=np.float64), types, end_sites


def read_deepmimic(path: str | Path, character: str | Path | None = None, *, what: str = "") -> RigMotion:
    """Read a DeepMimic motion; ``character`` defaults to the character file beside it. ``what`` (the
    option that named the motion file) leads the line when it is no file to read.

    fps comes from the frame durations (the last frame's, often 0, is ignored); uneven
    durations are resampled to the median rate.
    """
    path = Path(path)
    char_path = Path(character) if character is not None else find_character(path)
    names, parents, offsets, types, end_sites = read_character(char_path)
    data = _load_json(path, what)
    if "Frames" not in data:
        what = "a character file" if "Skeleton" in data else "not a motion"
        raise DeepMimicError(f"{path}: {what} (no \"Frames\" list)")
    frames = data["Frames"]
    dofs = [DOFS[t] for t in types[1:]]
    width = 8 + sum(dofs)
    if not isinstance(frames, list) or len(frames) == 0:
        raise DeepMimicError(f"{path}: the file has zero frames")
    bad = next((t for t, f in enumerate(frames) if not isinstance(f, list) or len(f) != width), None)
    if bad is not None:
        got = len(frames[bad]) if isinstance(frames[bad], list) else type(frames[bad]).__name__
        raise DeepMimicError(
            f"{path}: frame {bad} has {got} values, character {char_path.name} needs {width} "
            f"(duration 1 + root 7 + joints {sum(dofs)}: spherical 4, revolute 1, fixed 0)"
        )
    try:
        values = np.asarray(frames, dtype=np.float64)  # (T, width)
    except (TypeError, ValueError):
        raise DeepMimicError(f"{path}: a frame holds a value that is not a number") from None
    if not np.isfinite(values).all():
        t = int(np.nonzero(~np.isfinite(values).all(1))[0][0])
        raise DeepMimicError(f"{path}: frame {t} holds a non-finite number (NaN or inf)")

    T, J = len(values), len(names)
    rotations = np.zeros((T, J, 4))
    rotations[..., 0] = 1.0
    rotations[:, 0] = values[:, 4:8]
    column = 8
    for j, dof in enumerate(dofs, start=1):
        if dof == 4:
            rotations[:, j] = values[:, column : column + 4]
        elif dof == 1:  # revolute: an angle about Z
            half = values[:, column] / 2
            rotations[:, j, 0], rotations[:, j, 3] = np.cos(half), np.sin(half)
        column += dof
    norms = np.linalg.norm(rotations, axis=-1)
    if (norms < 1e-6).any():
        t = int(np.nonzero((norms < 1e-6).any(1))[0][0])
        raise DeepMimicError(f"{path}: frame {t} holds a zero quaternion")
    rotations = quat_normalize(torch.from_numpy(rotations)).numpy()
    translations = np.broadcast_to(offsets, (T, J, 3)).copy()
    translations[:, 0] = values[:, 1:4]

    durations = values[:-1, 0] if T > 1 else values[:, 0]
    step = float(np.median(durations))
    if step <= 0:
        raise DeepMimicError(f"{path}: frame durations must be positive, the median is {step}")
    fps = 1.0 / step
    if abs(step * round(fps) - 1.0) < 2e-4:  # 0.033332 s is 30 fps
        fps = float(round(fps))
    if T > 1 and np.abs(durations - step).max() > 1e-3 * step:
        times = np.concatenate([[0.0], np.cumsum(np.maximum(durations, 0.0))])  # (T,) seconds
        uniform = np.arange(int(math.floor(times[-1] * fps + 1e-6)) + 1) / fps
        rotations, translations = sample_frames(rotations, translations, np.interp(uniform, times, np.arange(T)))
    return RigMotion(
        name=path.stem,
        names=names,
        parents=parents,
        offsets=offsets,
        fps=fps,
        rotations=rotations,
        translations=translations,
        end_sites=end_sites,
        source=str(path),
    )
