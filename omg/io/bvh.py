"""BVH reader for any hierarchy, channel order and unit, and a writer for omg's skeletons.

A BVH joint's rotation channels compose intrinsically in the order they are listed
("Zrotation Xrotation Yrotation" gives R = Rz Rx Ry) and turn the offsets of its children.
Position channels, on any joint, replace that joint's offset for the frame (the reading
of Blender and most exporters). End Sites are not joints: they only count towards the
rest-pose size used to guess the unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES, atomic_write, read_file
from omg.io.rig import RigMotion
from omg.rotations import euler_to_quat, quat_to_euler
from omg.skeleton import Skeleton, get_skeleton

CM_ABOVE = 10.0  # a rest pose larger than this many units is taken to be in centimetres
CMU_SCALE = 0.0254 / 0.45  # metres per unit of CMU ASF/AMC and its BVH conversions (cgspeed): 1/0.45 inch
_CHANNELS = {f"{axis}{kind}".upper(): f"{axis}{kind}" for axis in "XYZ" for kind in ("position", "rotation")}


class BvhError(UsageError):
    """A malformed BVH file; the message names the file, the line where known, and the reason."""


def _error(src: str, line: int | None, reason: str) -> BvhError:
    return BvhError(f"{src}:{line}: {reason}" if line else f"{src}: {reason}")


def read_bvh(path: str | Path, scale: float | None = None, *, what: str = "") -> RigMotion:
    """Read a BVH file. ``scale`` multiplies lengths into metres; ``None`` takes CMU's BVH
    conversions (cgspeed rigs, with ``LHipJoint`` and ``RHipJoint`` joints) to be in CMU
    units (``CMU_SCALE``), other files to be in centimetres (0.01) when their rest pose (end
    sites included) is taller or wider than ``CM_ABOVE`` units, in metres otherwise. ``what``
    (the option that named the file, e.g. "--to_rig") leads the line when it is no file to read."""
    path = Path(path)
    src = str(path)
    lines = read_file(path, what, MOTION_MAX_BYTES).decode("utf-8", errors="replace").splitlines()
    names, parents, offsets, channels, end_sites, motion_line = _parse_hierarchy(lines, src)
    fps, values = _parse_motion(lines, motion_line, sum(len(c) for c in channels), src)

    rest = np.zeros((len(names), 3))
    for j, p in enumerate(parents):
        rest[j] = offsets[j] + (rest[p] if p >= 0 else 0.0)
    points = np.concatenate([rest] + [rest[p : p + 1] + off for p, off in end_sites])
    if scale is None and {"LHipJoint", "RHipJoint"} <= set(names):
        scale = CMU_SCALE
    elif scale is None:
        scale = 0.01 if (points.max(0) - points.min(0)).max() > CM_ABOVE else 1.0

    T, J = len(values), len(names)
    translations = np.broadcast_to(offsets, (T, J, 3)).copy()
    angles = np.zeros((T, J, 3))  # radians, in each joint's channel order
    orders: dict[str, list[int]] = {}  # Euler order -> joints
    column = 0
    for j, chans in enumerate(channels):
        cols = {c: column + i for i, c in enumerate(chans)}
        column += len(chans)
        for axis in range(3):
            if (c := "XYZ"[axis] + "position") in cols:
                translations[:, j, axis] = values[:, cols[c]]
        order = "".join(c[0] for c in chans if c.endswith("rotation"))
        angles[:, j, : len(order)] = np.deg2rad(values[:, [cols[a + "rotation"] for a in order]])
        # fewer than three rotation channels: the missing axes follow with zero angles
        orders.setdefault(order + "".join(a for a in "XYZ" if a not in order), []).append(j)
    rotations = torch.zeros(T, J, 4, dtype=torch.float64)
    for order, joints in orders.items():
        rotations[:, joints] = euler_to_quat(torch.from_numpy(angles[:, joints]), order)
    return RigMotion(
        name=path.stem,
        names=names,
        parents=parents,
        offsets=offsets * scale,
        channels=channels,
        fps=fps,
        rotations=rotations.numpy(),
        translations=translations * scale,
        end_sites=[(p, off * scale) for p, off in end_sites],
        source=src,
        unit=scale,
    )


def _floats(words: list[str], src: str, line: int, what: str = "number") -> np.ndarray:
    try:
        out = np.array(words, dtype=np.float64)
    except ValueError:
        for word in words:
            try:
                float(word)
            except ValueError:
                raise _error(src, line, f"bad {what} {word!r}") from None
        raise
    if not np.isfinite(out).all():
        raise _error(src, line, "non-finite number (NaN or inf)")
    return out


def _parse_hierarchy(lines: list[str], src: str):
    tokens: list[tuple[str, int]] = []
    motion_line = None
    for n, line in enumerate(lines, 1):
        words = line.split()
        if words and words[0].upper() == "MOTION":
            motion_line = n
            break
        tokens.extend((w, n) for w in words)
    if motion_line is None:
        raise _error(src, len(lines), "no MOTION section (truncated file?)")
    if not tokens:
        raise _error(src, motion_line, "no HIERARCHY before MOTION: the file holds no joints (no rig, no rest pose)")
    stream = iter(tokens)

    def take(what: str) -> tuple[str, int]:
        try:
            return next(stream)
        except StopIteration:
            raise _error(src, motion_line, f"HIERARCHY ends early, expected {what}") from None

    def expect(word: str) -> None:
        tok, n = take(repr(word))
        if tok.upper() != word.upper():
            raise _error(src, n, f"expected {word!r}, got {tok!r}")

    names, parents, offsets, channels, end_sites = [], [], [], [], []
    stack: list[tuple[str, int]] = []  # open blocks: ("joint", j) or ("end", k)
    expect("HIERARCHY")
    for tok, n in stream:
        key = tok.upper()
        if key in ("ROOT", "JOINT"):
            if (key == "ROOT") == bool(stack) or (stack and stack[-1][0] == "end"):
                raise _error(src, n, f"{tok} is not allowed here (one ROOT, JOINTs inside joints)")
            name, _ = take("a joint name")
            parents.append(stack[-1][1] if stack else -1)
            names.append(name)
            offsets.append(np.zeros(3))
            channels.append(())
            expect("{")
            stack.append(("joint", len(names) - 1))
        elif key == "END":
            if not stack or stack[-1][0] == "end":
                raise _error(src, n, "End Site outside a joint")
            expect("Site")
            expect("{")
            end_sites.append((stack[-1][1], np.zeros(3)))
            stack.append(("end", len(end_sites) - 1))
        elif key == "OFFSET" and stack:
            value = _floats([take("an OFFSET value")[0] for _ in range(3)], src, n, "OFFSET value (3 numbers needed)")
            kind, i = stack[-1]
            if kind == "joint":
                offsets[i] = value
            else:
                end_sites[i] = (end_sites[i][0], value)
        elif key == "CHANNELS" and stack and stack[-1][0] == "joint":
            count, _ = take("a channel count")
            if not count.isdigit():
                raise _error(src, n, f"bad channel count {count!r}")
            chans = []
            for _ in range(int(count)):
                word, m = take("a channel name")
                if word.upper() not in _CHANNELS:
                    raise _error(src, m, f"unknown channel {word!r} (expected X/Y/Z position or rotation)")
                chans.append(_CHANNELS[word.upper()])
            if len(set(chans)) != len(chans):
                raise _error(src, n, f"repeated channel in {' '.join(chans)}")
            channels[stack[-1][1]] = tuple(chans)
        elif tok == "}" and stack:
            stack.pop()
        else:
            raise _error(src, n, f"unexpected {tok!r} in HIERARCHY")
    if stack or not names:
        raise _error(src, motion_line, "MOTION before the hierarchy is complete (missing joints or '}')")
    return names, parents, np.array(offsets), channels, end_sites, motion_line


def _parse_motion(lines: list[str], motion_line: int, num_channels: int, src: str) -> tuple[float, np.ndarray]:
    rest = [(line.split(), n) for n, line in enumerate(lines[motion_line:], motion_line + 1) if line.strip()]
    if len(rest) < 2:
        raise _error(src, len(lines), "MOTION needs 'Frames:' and 'Frame Time:' lines (truncated file?)")
    (frames_words, n1), (time_words, n2) = rest[:2]
    if len(frames_words) != 2 or frames_words[0].upper() != "FRAMES:" or not frames_words[1].isdigit():
        raise _error(src, n1, f"expected 'Frames: <count>', got {' '.join(frames_words)!r}")
    if len(time_words) != 3 or [w.upper() for w in time_words[:2]] != ["FRAME", "TIME:"]:
        raise _error(src, n2, f"expected 'Frame Time: <seconds>', got {' '.join(time_words)!r}")
    frame_time = float(_floats(time_words[2:], src, n2)[0])
    if frame_time <= 0:
        raise _error(src, n2, f"Frame Time must be positive, got {frame_time}")
    num_frames, frames = int(frames_words[1]), rest[2:]
    if num_frames == 0:
        raise _error(src, n1, "the file has zero frames")
    if len(frames) != num_frames:
        where = frames[num_frames][1] if len(frames) > num_frames else len(lines)
        raise _error(src, where, f"'Frames: {num_frames}' but {len(frames)} frame lines follow (truncated file?)")
    values = np.empty((num_frames, num_channels))
    for t, (words, n) in enumerate(frames):
        if len(words) != num_channels:
            raise _error(src, n, f"frame line has {len(words)} values, the channels need {num_channels}")
        values[t] = _floats(words, src, n)
    fps = 1.0 / frame_time
    # "Frame Time: .0083333" means 120 fps; 29.97 fps stays 29.97
    return (float(round(fps)) if abs(frame_time * round(fps) - 1.0) < 1e-4 else fps), values


def write_bvh(
    path: str | Path,
    skeleton: Skeleton | str,
    rotations: np.ndarray | torch.Tensor,  # (T, J, 4) local quaternions (w, x, y, z)
    root_positions: np.ndarray | torch.Tensor,  # (T, 3) metres
    fps: float,
    offsets: np.ndarray | None = None,  # (J, 3) metres; the skeleton's rest offsets if None
    order: str = "ZXY",
    scale: float = 1.0,  # file units per metre (100 for centimetres)
) -> Path:
    """Write a motion as a standard BVH file, atomically; ``read_bvh`` gives back its positions.

    The root has position channels then rotation channels, every other joint rotation
    channels only, all in the Euler ``order``; leaf joints end in an End Site half as long
    as their own bone. Joints appear depth first, so the file's joint order can differ from
    the skeleton's (SMPL-22's is breadth first): match joints by name when reading back.
    """
    skel = get_skeleton(skeleton)
    order = order.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"Euler order {order!r} must use each of X, Y, Z once (e.g. 'ZXY')")
    J = skel.num_joints
    rot = torch.as_tensor(rotations, dtype=torch.float64)
    root = np.asarray(root_positions, dtype=np.float64)
    if rot.ndim != 3 or rot.shape[1:] != (J, 4) or root.shape != (rot.shape[0], 3) or rot.shape[0] == 0:
        raise ValueError(
            f"write_bvh: rotations must be (T, {J}, 4) and root_positions (T, 3) with T > 0 for skeleton "
            f"{skel.name!r}, got {tuple(rot.shape)} and {root.shape}"
        )
    off = np.asarray(skel.rest_offsets if offsets is None else offsets, dtype=np.float64) * scale  # (J, 3)
    rotation_channels = " ".join(f"{axis}rotation" for axis in order)
    lines, joints = ["HIERARCHY"], []  # joints: depth-first order of the file

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        # the root's OFFSET is zero so that both readings of its position channels (absolute,
        # or added to the offset) place it alike
        offset = np.zeros(3) if j == 0 else off[j]
        channels = f"6 Xposition Yposition Zposition {rotation_channels}" if j == 0 else f"3 {rotation_channels}"
        name = "_".join(skel.names[j].split())  # a BVH name ends at whitespace
        lines.extend([f"{pad}{'ROOT' if j == 0 else 'JOINT'} {name}", f"{pad}{{",
                      f"{pad}  OFFSET {_fmt(offset)}", f"{pad}  CHANNELS {channels}"])  # fmt: skip
        joints.append(j)
        children = skel.children(j)
        for c in children:
            emit(c, depth + 1)
        if not children:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_fmt(0.5 * off[j])}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    angles = np.rad2deg(quat_to_euler(rot[:, joints], order).numpy())  # (T, J, 3) in the file's joint order
    values = np.concatenate([root * scale, angles.reshape(len(root), -1)], axis=1)  # (T, 3 + 3J)
    lines += ["MOTION", f"Frames: {len(values)}", f"Frame Time: {1.0 / fps:.8f}"]
    lines += [_fmt(row) for row in values]
    path = Path(path)
    atomic_write(path, ("\n".join(lines) + "\n").encode())
    return path


def _fmt(vector: np.ndarray) -> str:
    return " ".join(f"{v:.6f}" for v in vector)


def write_rig_bvh(path: str | Path, motion: RigMotion) -> Path:
    """Write a motion on its own rig (``RigMotion``, e.g. ``omg.retarget.onto_rig``'s) as BVH, atomically:
    the rig's hierarchy, joint names, channels (order included), end sites and unit (``motion.unit``).

    Position channels get the joint's translation (the reader's meaning: they replace the offset);
    rotation channels the Euler angles of its local rotation in the listed order. A joint with fewer
    than three rotation channels keeps only those axes (the reader completes the order the same way).
    """
    unit = motion.unit or 1.0
    J = motion.num_joints
    channels = motion.channels or [("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")] + [
        ("Zrotation", "Xrotation", "Yrotation")
    ] * (J - 1)
    children = [[c for c, p in enumerate(motion.parents) if p == j] for j in range(J)]
    ends = [[off for p, off in motion.end_sites if p == j] for j in range(J)]
    lines, joints = ["HIERARCHY"], []

    def emit(j: int, depth: int) -> None:
        pad = "  " * depth
        name = "_".join(motion.names[j].split())
        lines.extend([f"{pad}{'ROOT' if j == 0 else 'JOINT'} {name}", f"{pad}{{",
                      f"{pad}  OFFSET {_fmt(motion.offsets[j] / unit)}",
                      f"{pad}  CHANNELS {len(channels[j])} {' '.join(channels[j])}".rstrip()])  # fmt: skip
        joints.append(j)
        for c in children[j]:
            emit(c, depth + 1)
        for off in ends[j]:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_fmt(off / unit)}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    rot = torch.as_tensor(np.asarray(motion.rotations), dtype=torch.float64)
    columns = []
    for j in joints:
        chans = channels[j]
        order = "".join(c[0] for c in chans if c.endswith("rotation"))
        full = order + "".join(a for a in "XYZ" if a not in order)
        angles = np.rad2deg(quat_to_euler(rot[:, j], full).numpy()) if order else None  # (T, 3)
        for c in chans:
            if c.endswith("position"):
                columns.append(motion.translations[:, j, "XYZ".index(c[0])] / unit)
            else:
                columns.append(angles[:, order.index(c[0])])
    T = len(motion)
    values = np.stack(columns, axis=1) if columns else np.zeros((T, 0))
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {1.0 / motion.fps:.8f}"]
    lines += [_fmt(row) for row in values]
    path = Path(path)
    atomic_write(path, ("\n".join(lines) + "\n").encode())
    return path
