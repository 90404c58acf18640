"""BVH reader for any hierarchy, channel order and unit, and a writer for omg's skeletons.

A BVH joint's rotation channels compose intrinsically in the order they are listed
("Zrotation Xrotation Yrotation" gives R = Rz Rx Ry) and turn the offsets of its children.
Position channels, on any joint, replace that joint's offset for the frame (the reading
of Blender and most exporters). End Sites are not joints: they only count towards the
rest-pose size used to guess the unit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from omg.data.shards import atomic_write
from omg.errors import UsageError
from omg.motion.base import Clip
from omg.rotations import euler_to_quat, quat_apply, quat_mul, quat_to_euler
from omg.skeleton import Skeleton, get_skeleton

CM_ABOVE = 10.0  # a rest pose larger than this many units is taken to be in centimetres
CMU_SCALE = 0.0254 / 0.45  # metres per unit of CMU ASF/AMC and its BVH conversions (cgspeed): 1/0.45 inch
_CHANNELS = {f"{axis}{kind}".upper(): f"{axis}{kind}" for axis in "XYZ" for kind in ("position", "rotation")}


class BvhError(UsageError):
    """A malformed BVH file; the message names the file, the line where known, and the reason."""


def _error(src: str, line: int | None, reason: str) -> BvhError:
    return BvhError(f"{src}:{line}: {reason}" if line else f"{src}: {reason}")


@dataclass
class BvhMotion:
    """The hierarchy and animation of one BVH file, in metres and quaternions."""

    name: str  # file stem
    names: list[str]
    parents: list[int]  # -1 for the root; parents[j] < j
    offsets: np.ndarray  # (J, 3) rest offsets in metres; row 0 is the root's
    channels: list[tuple[str, ...]]  # per joint, as listed in the file
    fps: float
    rotations: np.ndarray  # (T, J, 4) local quaternions (w, x, y, z)
    translations: np.ndarray  # (T, J, 3) metres: position channels where a joint has them, its offset elsewhere
    end_sites: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (parent joint, (3,) offset in metres)
    source: str = ""  # the file it was read from

    def __len__(self) -> int:
        return self.rotations.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def skeleton(self, name: str | None = None) -> Skeleton:
        return Skeleton.from_parents(name or self.name, self.parents, self.offsets, names=self.names)

    def positions(self) -> np.ndarray:
        """(T, J, 3) global joint positions by forward kinematics with the per-frame translations."""
        rot, trans = torch.from_numpy(self.rotations), torch.from_numpy(self.translations)
        return self.skeleton().forward_kinematics(rot, trans[:, 0], offsets=trans).numpy()

    def merge_root(self) -> BvhMotion:
        """Fold the root into its only child joint, which becomes the new root.

        For rigs whose root is a static parent of the moving hips (Bandai-Namco's
        ``joint_Root``): afterwards the root carries the whole global motion, so that the
        motion is described by local rotations, static bone offsets and a root trajectory.
        """
        children = [j for j, p in enumerate(self.parents) if p == 0]
        if children != [1] or any(p == 0 for p, _ in self.end_sites):
            raise _error(self.source, None, f"cannot merge root {self.names[0]!r}: it must have one child joint only")
        rot, trans = torch.from_numpy(self.rotations).clone(), torch.from_numpy(self.translations).clone()
        rot[:, 1] = quat_mul(rot[:, 0], rot[:, 1])
        trans[:, 1] = trans[:, 0] + quat_apply(rot[:, 0], trans[:, 1])
        offsets = self.offsets[1:].copy()
        offsets[0] += self.offsets[0]  # rest rotations are the identity
        return replace(
            self,
            names=self.names[1:],
            parents=[-1] + [p - 1 for p in self.parents[2:]],
            offsets=offsets,
            channels=self.channels[1:],
            rotations=rot[:, 1:].numpy(),
            translations=trans[:, 1:].numpy(),
            end_sites=[(p - 1, off) for p, off in self.end_sites],
        )

    def to_clip(
        self, id: str | None = None, skeleton: Skeleton | str | None = None, texts: Sequence[str] = (), **fields
    ) -> Clip:
        """A clip with positions by FK, and rotations + offsets where these describe the motion.

        Position channels that move a non-root joint more than 1 mm away from its rest
        offset cannot be expressed by (rotations, static offsets); such clips carry
        positions only (see ``merge_root`` for rigs whose hips move below a static root).
        """
        skel = self.skeleton() if skeleton is None else get_skeleton(skeleton)
        if skel.num_joints != self.num_joints:
            raise UsageError(
                f"{self.source}: skeleton {skel.name!r} has {skel.num_joints} joints, the BVH file {self.num_joints}"
            )
        rigid = np.abs(self.translations[:, 1:] - self.offsets[1:]).max(initial=0.0) <= 1e-3
        return Clip(
            id=id or self.name,
            skeleton=skel,
            fps=self.fps,
            positions=self.positions().astype(np.float32),
            rotations=self.rotations.astype(np.float32) if rigid else None,
            offsets=self.offsets.astype(np.float32) if rigid else None,
            texts=list(texts),
            source=self.source,
            **fields,
        )


def read_bvh(path: str | Path, scale: float | None = None) -> BvhMotion:
    """Read a BVH file. ``scale`` multiplies lengths into metres; ``None`` takes the file to be
    in centimetres (0.01) when its rest pose (end sites included) is taller or wider than
    ``CM_ABOVE`` units, in metres otherwise. CMU's BVH conversions need ``scale=CMU_SCALE``."""
    path = Path(path)
    src = str(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as e:
        raise _error(src, None, f"cannot read the file ({e.strerror})") from None
    names, parents, offsets, channels, end_sites, motion_line = _parse_hierarchy(lines, src)
    fps, values = _parse_motion(lines, motion_line, sum(len(c) for c in channels), src)

    rest = np.zeros((len(names), 3))
    for j, p in enumerate(parents):
        rest[j] = offsets[j] + (rest[p] if p >= 0 else 0.0)
    points = np.concatenate([rest] + [rest[p : p + 1] + off for p, off in end_sites])
    if scale is None:
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
    return BvhMotion(
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
