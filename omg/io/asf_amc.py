"""Acclaim ASF (skeleton) / AMC (motion) files, as in the CMU motion capture database.

ASF: ``:units`` (``length`` multiplier, ``angle deg|rad``), ``:root`` (``order`` of the
AMC root values, e.g. ``TX TY TZ RX RY RZ``, and the rotation ``axis`` order), ``:bonedata``
(per bone: ``direction`` (unit vector, global rest frame), ``length``, ``axis ax ay az
ORDER`` (the bone's local frame C), ``dof`` (the AMC values, a subset of ``rx ry rz``)) and
``:hierarchy`` (``parent child child ...``). AMC: optional ``:DEGREES``/``:RADIANS``, then
per frame its number and one line ``bone values...`` per bone with dofs.

Bone b's rotation relative to its parent is ``C M C^-1`` with M from the AMC values, and it
turns b's own vector (direction * length). In ``RigMotion`` terms each bone becomes a joint
at the bone's start (named after the bone) and its vector becomes its children's offset (or
an end site), which is how CMU's BVH conversions lay the same rigs out. Euler angles apply
in the listed order about fixed axes ("XYZ": R = Rz Ry Rx).

Units: CMU's ``length 0.45`` means a file unit is 1/0.45 inch, so metres = value * 0.0254 /
length (``omg.io.bvh.CMU_SCALE`` for CMU). AMC has no frame rate: 120 fps (CMU) unless given.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES, read_file
from omg.io.rig import RigMotion
from omg.rotations import euler_to_quat, quat_conjugate, quat_mul

AMC_FPS = 120.0
_AXES = ("rx", "ry", "rz")


class AsfAmcError(UsageError):
    """A malformed ASF or AMC file; the message names the file, the line where known, and the reason."""


def _error(src, line: int | None, reason: str) -> AsfAmcError:
    return AsfAmcError(f"{src}:{line}: {reason}" if line else f"{src}: {reason}")


def _numbers(words: list[str], src, line: int, count: int | None = None) -> list[float]:
    if count is not None and len(words) < count:
        raise _error(src, line, f"expected {count} numbers, got {' '.join(words)!r}")
    try:
        out = [float(w) for w in (words if count is None else words[:count])]
    except ValueError:
        raise _error(src, line, f"bad number in {' '.join(words)!r}") from None
    if not np.isfinite(out).all():
        raise _error(src, line, "non-finite number (NaN or inf)")
    return out


def _fixed_axes_quat(angles: np.ndarray, order: str) -> torch.Tensor:
    """(..., 3) radians, one per letter of ``order``, applied in that order about fixed axes."""
    return euler_to_quat(torch.from_numpy(np.ascontiguousarray(angles[..., ::-1])), order[::-1])


def read_asf(path: str | Path) -> dict:
    """The skeleton of an ASF file as a dict: units, root spec, bones, hierarchy."""
    path = Path(path)
    lines = read_file(path, "", MOTION_MAX_BYTES).decode("utf-8", errors="replace").splitlines()
    asf = {"length": 1.0, "degrees": True, "root_order": ["TX", "TY", "TZ", "RX", "RY", "RZ"], "root_axis": "XYZ",
           "root_position": np.zeros(3), "root_orientation": np.zeros(3), "bones": {}, "children": {}}  # fmt: skip
    section, bone, n_bone = None, None, 0
    for n, line in enumerate(lines, 1):
        words = line.split("#")[0].split()
        if not words:
            continue
        key = words[0].lower()
        if key.startswith(":"):
            section = key[1:]
            if section == "name" or section == "version":
                section = None
            continue
        if section == "units":
            if key == "length":
                asf["length"] = _numbers(words[1:], path, n, 1)[0]
                if asf["length"] <= 0:
                    raise _error(path, n, f"length multiplier must be positive, got {words[1]}")
            elif key == "angle":
                if len(words) < 2 or words[1].lower() not in ("deg", "rad"):
                    raise _error(path, n, f"angle unit must be deg or rad, got {' '.join(words[1:])!r}")
                asf["degrees"] = words[1].lower() == "deg"
        elif section == "root":
            if key == "order":
                order = [w.upper() for w in words[1:]]
                if not set(order) <= {"TX", "TY", "TZ", "RX", "RY", "RZ"} or len(set(order)) != len(order):
                    raise _error(path, n, f"bad root order {' '.join(words[1:])!r}")
                asf["root_order"] = order
            elif key == "axis":
                asf["root_axis"] = _order(words[1:], path, n)
            elif key == "position":
                asf["root_position"] = np.array(_numbers(words[1:], path, n, 3))
            elif key == "orientation":
                asf["root_orientation"] = np.array(_numbers(words[1:], path, n, 3))
        elif section == "bonedata":
            if key == "begin":
                bone, n_bone = {"dof": [], "axis": np.zeros(3), "order": "XYZ"}, n
            elif key == "end":
                if bone is None or not {"name", "direction", "length"} <= bone.keys():
                    raise _error(path, n, "bone block without name, direction or length")
                asf["bones"][bone["name"]] = bone
                bone = None
            elif bone is None:
                raise _error(path, n, f"{words[0]!r} outside a begin/end bone block")
            elif key == "name":
                bone["name"] = words[1]
            elif key == "direction":
                bone["direction"] = np.array(_numbers(words[1:], path, n, 3))
            elif key == "length":
                bone["length"] = _numbers(words[1:], path, n, 1)[0]
            elif key == "axis":
                bone["axis"] = np.array(_numbers(words[1:], path, n, 3))
                bone["order"] = _order(words[4:], path, n)
            elif key == "dof":
                dof = [w.lower() for w in words[1:]]
                if not set(dof) <= set(_AXES) or len(set(dof)) != len(dof):
                    raise _error(path, n, f"unsupported dof {' '.join(words[1:])!r} (rotations rx ry rz only)")
                bone["dof"] = dof
        elif section == "hierarchy":
            if key in ("begin", "end"):
                continue
            asf["children"].setdefault(words[0], []).extend(words[1:])
    if bone is not None:
        raise _error(path, n_bone, "bone block not closed with 'end' (truncated file?)")
    if not asf["bones"] or "root" not in asf["children"]:
        raise _error(path, None, "no :bonedata or no :hierarchy starting at root")
    for parent, kids in asf["children"].items():
        for name in [parent, *kids]:
            if name != "root" and name not in asf["bones"]:
                raise _error(path, None, f"hierarchy names bone {name!r}, which :bonedata does not define")
    return asf


def _order(words: list[str], src, line: int) -> str:
    order = words[0].upper() if words else "XYZ"
    if sorted(order) != ["X", "Y", "Z"]:
        raise _error(src, line, f"bad axis order {order!r} (a permutation of XYZ)")
    return order


def read_amc(
    path: str | Path, asf: str | Path | None = None, fps: float = AMC_FPS, scale: float | None = None, *,
    what: str = "",
) -> RigMotion:
    """Read an AMC motion with its ASF skeleton (default: ``NN.asf`` beside ``NN_MM.amc``).

    ``scale`` (metres per file unit) defaults to 0.0254 / the ASF length multiplier; ``what`` (the
    option that named the AMC file) leads the line when it is no file to read.
    """
    path = Path(path)
    asf_path = Path(asf) if asf is not None else find_asf(path)
    skel = read_asf(asf_path)
    scale = 0.0254 / skel["length"] if scale is None else scale
    if fps <= 0:
        raise _error(path, None, f"fps must be positive, got {fps}")

    # joints: root, then bones depth first
    names, parents, bones = ["root"], [-1], [None]
    stack = [(c, 0) for c in reversed(skel["children"]["root"])]
    while stack:
        name, parent = stack.pop()
        if name in names:
            raise _error(asf_path, None, f"bone {name!r} appears twice in the hierarchy")
        names.append(name)
        parents.append(parent)
        bones.append(skel["bones"][name])
        stack.extend((c, len(names) - 1) for c in reversed(skel["children"].get(name, [])))
    J = len(names)
    vectors = np.zeros((J, 3))  # each bone's rest vector (start -> end) in metres
    for j in range(1, J):
        vectors[j] = bones[j]["direction"] * bones[j]["length"] * scale
    offsets = np.zeros((J, 3))
    offsets[0] = skel["root_position"] * scale
    for j in range(1, J):
        offsets[j] = vectors[parents[j]]  # the parent bone's end; 0 under the root
    has_children = {p for p in parents if p >= 0}
    end_sites = [(j, vectors[j]) for j in range(1, J) if j not in has_children]

    frames = _parse_amc(path, skel, names, bones, what)
    T = len(frames)
    to_rad = np.pi / 180.0 if frames.degrees else 1.0  # AMC values
    asf_rad = np.pi / 180.0 if skel["degrees"] else 1.0  # ASF axes and orientation
    rotations = torch.zeros(T, J, 4, dtype=torch.float64)
    rotations[..., 0] = 1.0
    # root: its values in "order"; rotation composed in the root axis order, frame from "orientation"
    order = skel["root_order"]
    root = frames.root  # (T, len(order))
    axis = skel["root_axis"]
    angles = np.zeros((T, 3))
    for i, letter in enumerate(axis):
        if f"R{letter}" in order:
            angles[:, i] = root[:, order.index(f"R{letter}")] * to_rad
    c_root = _fixed_axes_quat(skel["root_orientation"][["XYZ".index(a) for a in axis]] * asf_rad, axis)
    rotations[:, 0] = quat_mul(quat_mul(c_root, _fixed_axes_quat(angles, axis)), quat_conjugate(c_root))
    translations = np.broadcast_to(offsets, (T, J, 3)).copy()
    for i, letter in enumerate("XYZ"):
        if f"T{letter}" in order:
            translations[:, 0, i] = root[:, order.index(f"T{letter}")] * scale
    for j in range(1, J):
        bone = bones[j]
        if not bone["dof"]:
            continue  # no motion: C I C^-1 is the identity
        c = _fixed_axes_quat(bone["axis"][["XYZ".index(a) for a in bone["order"]]] * asf_rad, bone["order"])
        values = frames.bones[names[j]] * to_rad  # (T, len(dof))
        dof_order = "".join(d[1].upper() for d in bone["dof"])
        full = dof_order + "".join(a for a in "XYZ" if a not in dof_order)
        padded = np.zeros((T, 3))
        padded[:, : len(dof_order)] = values
        m = _fixed_axes_quat(padded, full)
        rotations[:, j] = quat_mul(quat_mul(c.expand(T, 4), m), quat_conjugate(c).expand(T, 4))
    return RigMotion(
        name=path.stem,
        names=names,
        parents=parents,
        offsets=offsets,
        fps=float(fps),
        rotations=rotations.numpy(),
        translations=translations,
        end_sites=end_sites,
        source=str(path),
    )


def find_asf(amc_path: str | Path) -> Path:
    """The skeleton of ``NN_MM.amc``: ``NN.asf`` beside it, else the only .asf there."""
    amc_path = Path(amc_path)
    subject = re.split(r"[_\-]", amc_path.stem)[0]
    named = amc_path.with_name(f"{subject}.asf")
    if named.exists():
        return named
    candidates = sorted(amc_path.parent.glob("*.asf"))
    if len(candidates) == 1:
        return candidates[0]
    raise _error(amc_path, None, f"no skeleton file {named.name} beside it; pass asf=PATH")


class _Frames:
    def __init__(self, degrees: bool, root: np.ndarray, bones: dict[str, np.ndarray]):
        self.degrees, self.root, self.bones = degrees, root, bones

    def __len__(self) -> int:
        return len(self.root)


def _parse_amc(path: Path, skel: dict, names: list[str], bones: list, what: str = "") -> _Frames:
    lines = read_file(path, what, MOTION_MAX_BYTES).decode("utf-8", errors="replace").splitlines()
    degrees = skel["degrees"]
    widths = {"root": len(skel["root_order"])}
    widths.update({names[j]: len(bones[j]["dof"]) for j in range(1, len(names)) if bones[j]["dof"]})
    frames: list[dict[str, list[float]]] = []
    starts: list[int] = []
    for n, line in enumerate(lines, 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        if words[0].startswith(":"):
            key = words[0].upper()
            if key in (":DEGREES", ":RADIANS"):
                degrees = key == ":DEGREES"
            continue
        if len(words) == 1 and words[0].isdigit():
            frames.append({})
            starts.append(n)
            continue
        if not frames:
            raise _error(path, n, f"{words[0]!r} before the first frame number")
        name = words[0]
        if name not in widths:
            known = "no such bone" if name not in names else "the bone has no dof"
            raise _error(path, n, f"values for {name!r}, but {known} in the ASF")
        if len(words) - 1 != widths[name]:
            raise _error(path, n, f"{name} has {len(words) - 1} values, its dof needs {widths[name]}")
        frames[-1][name] = _numbers(words[1:], path, n)
    if not frames:
        raise _error(path, None, "the file has zero frames")
    for t, frame in enumerate(frames):
        missing = [b for b in widths if b not in frame]
        if missing:
            raise _error(path, starts[t], f"frame {t + 1} lacks {', '.join(missing[:5])} (truncated file?)")
    return _Frames(
        degrees,
        np.array([f["root"] for f in frames], dtype=np.float64),
        {b: np.array([f[b] for f in frames], dtype=np.float64) for b in widths if b != "root"},
    )
