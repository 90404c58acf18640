"""``RigMotion``: the hierarchy and animation of one motion file, the common output of every
reader (BVH, DeepMimic JSON, ASF/AMC) and the input of retargeting.

Conventions are the skeleton module's: metres, local quaternions (w, x, y, z) where joint
j's rotation turns the offsets of its children, rest rotations the identity. The up axis
and facing are whatever the file uses (retargeting detects them).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from omg.errors import UsageError
from omg.motion.base import Clip
from omg.rotations import quat_apply, quat_mul, quat_slerp
from omg.skeleton import Skeleton, get_skeleton


@dataclass
class RigMotion:
    """One motion on its own rig, in metres and quaternions."""

    name: str  # file stem
    names: list[str]
    parents: list[int]  # -1 for the root; parents[j] < j
    offsets: np.ndarray  # (J, 3) rest offsets in metres; row 0 is the root's
    fps: float
    rotations: np.ndarray  # (T, J, 4) local quaternions (w, x, y, z)
    translations: np.ndarray  # (T, J, 3) metres: position channels where a joint has them, its offset elsewhere
    end_sites: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (parent joint, (3,) offset in metres)
    source: str = ""  # the file it was read from
    channels: list[tuple[str, ...]] = field(default_factory=list)  # BVH only: per joint, as listed in the file
    unit: float = 1.0  # metres per unit of the file (BVH: 0.01 for centimetres), so a writer keeps the file's unit
    character: object | None = None  # a glTF character's document (``omg.io.gltf.Character``): its writer adds to it

    def __len__(self) -> int:
        return self.rotations.shape[0]

    @property
    def sole(self) -> float | None:
        """A character's sole: the height (m) of its skinned meshes' lowest point at rest; None for a rig without a
        mesh (a BVH file, a skeleton-only glTF), whose feet stand where its own frames put them."""
        return getattr(self.character, "sole", None)

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def skeleton(self, name: str | None = None) -> Skeleton:
        return Skeleton.from_parents(name or self.name, self.parents, self.offsets, names=self.names)

    def positions(self) -> np.ndarray:
        """(T, J, 3) global joint positions by forward kinematics with the per-frame translations."""
        rot, trans = torch.from_numpy(self.rotations), torch.from_numpy(self.translations)
        return self.skeleton().forward_kinematics(rot, trans[:, 0], offsets=trans).numpy()

    def end_site_names(self) -> list[str]:
        """Names that address the end sites in joint maps: ``<parent>_end`` (``_end1``, ... for more)."""
        seen: dict[int, int] = {}
        out = []
        for p, _ in self.end_sites:
            k = seen[p] = seen.get(p, -1) + 1
            out.append(f"{self.names[p]}_end" + (str(k) if k else ""))
        return out

    def positions_with_end_sites(self) -> np.ndarray:
        """(T, J + E, 3): joint positions, then end-site positions in ``end_sites`` order."""
        rot, trans = torch.from_numpy(self.rotations), torch.from_numpy(self.translations)
        skel = self.skeleton()
        pos = skel.forward_kinematics(rot, trans[:, 0], offsets=trans)
        if not self.end_sites:
            return pos.numpy()
        glob = skel.global_rotations(rot)  # (T, J, 4)
        parents = [p for p, _ in self.end_sites]
        off = torch.from_numpy(np.stack([o for _, o in self.end_sites])).to(pos.dtype)  # (E, 3)
        ends = pos[:, parents] + quat_apply(glob[:, parents], off.expand(len(self), -1, -1))
        return torch.cat([pos, ends], dim=1).numpy()

    def rest_positions(self, end_sites: bool = False) -> np.ndarray:
        """(J, 3) joint positions of the rest pose (all rotations identity, root at its offset),
        followed by the end sites' (E, 3) when ``end_sites``."""
        rest = np.zeros((self.num_joints, 3))
        for j, p in enumerate(self.parents):
            rest[j] = self.offsets[j] + (rest[p] if p >= 0 else 0.0)
        if end_sites and self.end_sites:
            rest = np.concatenate([rest, np.stack([rest[p] + off for p, off in self.end_sites])])
        return rest

    def rescaled(self, factor: float) -> RigMotion:
        """Every length multiplied by ``factor`` (a unit change)."""
        return replace(
            self,
            offsets=self.offsets * factor,
            translations=self.translations * factor,
            end_sites=[(p, off * factor) for p, off in self.end_sites],
        )

    def resample(self, fps: float) -> RigMotion:
        """The motion at ``fps``: slerped rotations, linearly interpolated translations.

        Frame k of the result lies at source frame k * self.fps / fps; at integer ratios (120
        -> 20, 30 -> 60) every output frame that falls on a source frame is that frame exactly.
        """
        if fps <= 0:
            raise UsageError(f"{self.source or self.name}: cannot resample to {fps} fps (must be positive)")
        if abs(fps - self.fps) < 1e-9:
            return self
        n = int(np.floor((len(self) - 1) * fps / self.fps + 1e-6)) + 1
        where = np.arange(n) * self.fps / fps  # (n,) fractional source frames
        rotations, translations = sample_frames(self.rotations, self.translations, where)
        return replace(self, fps=float(fps), rotations=rotations, translations=translations)

    def merge_root(self) -> RigMotion:
        """Fold the root into its only child joint, which becomes the new root.

        For rigs whose root is a static parent of the moving hips (Bandai-Namco's
        ``joint_Root``): afterwards the root carries the whole global motion, so that the
        motion is described by local rotations, static bone offsets and a root trajectory.
        """
        children = [j for j, p in enumerate(self.parents) if p == 0]
        if children != [1] or any(p == 0 for p, _ in self.end_sites):
            raise UsageError(
                f"{self.source or self.name}: cannot merge root {self.names[0]!r}: it must have one child joint only"
            )
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
        """A clip on this rig (no retargeting): positions by FK, and rotations + offsets where
        these describe the motion.

        Translations that move a non-root joint more than 1 mm away from its rest offset
        cannot be expressed by (rotations, static offsets); such clips carry positions only
        (see ``merge_root`` for rigs whose hips move below a static root, and
        ``omg.retarget`` for clips on the model skeletons).
        """
        skel = self.skeleton() if skeleton is None else get_skeleton(skeleton)
        if skel.num_joints != self.num_joints:
            raise UsageError(
                f"{self.source}: skeleton {skel.name!r} has {skel.num_joints} joints, the motion file {self.num_joints}"
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


def sample_frames(rotations: np.ndarray, translations: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (T, J, 4) and translations (T, J, 3) at fractional frame indices ``where`` (n,)
    in [0, T - 1]: slerp and lerp between the two frames around each; whole indices exact."""
    T = rotations.shape[0]
    where = np.clip(np.asarray(where, dtype=np.float64), 0.0, T - 1)
    i0 = np.floor(where + 1e-9).astype(np.int64).clip(max=T - 1)
    i1 = np.minimum(i0 + 1, T - 1)
    w = where - i0
    w[np.abs(w) < 1e-9] = 0.0
    rot = torch.from_numpy(np.asarray(rotations, dtype=np.float64))
    a, b = rot[i0], rot[i1]  # (n, J, 4)
    wt = torch.from_numpy(w)[:, None, None]  # (n, 1, 1)
    slerped = quat_slerp(a, b, wt.expand(-1, a.shape[1], 1))
    out_rot = torch.where(wt == 0, a, slerped)  # whole indices: the frame itself, bit for bit
    tr = np.asarray(translations, dtype=np.float64)
    out_tr = tr[i0] + w[:, None, None] * (tr[i1] - tr[i0])
    return out_rot.numpy(), out_tr
