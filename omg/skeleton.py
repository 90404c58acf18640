"""Skeletons: joint hierarchy, rest pose and semantic joint groups, plus forward kinematics.

Coordinates are metres, +Y up; a character in its rest pose faces +Z with its left side
towards +X (the SMPL and HumanML3D convention). Local rotations are quaternions (w, x, y, z)
in the BVH convention: joint j's rotation turns the offsets of its children, so
``p[j] = p[parent] + R_global[parent] · offset[j]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from omg.registry import SKELETONS
from omg.rotations import quat_apply, quat_mul


@dataclass(frozen=True)
class Skeleton:
    """A joint hierarchy with its rest offsets and the joint groups models and metrics use.

    ``parents[j] < j`` for every non-root joint (topological order), root first with -1.
    """

    name: str
    names: tuple[str, ...]
    parents: tuple[int, ...]
    rest_offsets: np.ndarray  # (J, 3) metres; row 0 is the root's rest position
    chains: tuple[tuple[int, ...], ...] = ()
    face_joints: tuple[int, ...] = ()  # (right hip, left hip, right shoulder, left shoulder)
    feet_left: tuple[int, ...] = ()
    feet_right: tuple[int, ...] = ()
    primal_joints: tuple[int, ...] = ()
    end_effectors: tuple[int, ...] = ()
    symmetry: tuple[int, ...] = ()  # joint j's mirror image is symmetry[j]
    leg_bone: tuple[int, int] | None = None  # (joint, child) whose length sets the scale
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        J = len(self.names)
        offsets = np.asarray(self.rest_offsets, dtype=np.float32).reshape(J, 3)
        object.__setattr__(self, "rest_offsets", offsets)
        if len(self.parents) != J:
            raise ValueError(f"skeleton {self.name!r}: {len(self.parents)} parents for {J} joints")
        if self.parents[0] != -1 or any(not (0 <= p < j) for j, p in enumerate(self.parents) if j):
            raise ValueError(
                f"skeleton {self.name!r}: parents must list the root first with -1 and every "
                f"other joint after its parent, got {list(self.parents)}"
            )
        for field_name in ("chains", "face_joints", "feet_left", "feet_right", "primal_joints", "end_effectors"):
            group = getattr(self, field_name)
            joints = [j for chain in group for j in chain] if field_name == "chains" else group
            bad = [j for j in joints if not 0 <= j < J]
            if bad:
                raise ValueError(f"skeleton {self.name!r}: {field_name} has joints {bad} outside 0..{J - 1}")
        if self.symmetry and sorted(self.symmetry) != list(range(J)):
            raise ValueError(f"skeleton {self.name!r}: symmetry must be a permutation of 0..{J - 1}")

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def feet(self) -> tuple[int, ...]:
        return self.feet_left + self.feet_right

    def index(self, joint_name: str) -> int:
        try:
            return self.names.index(joint_name)
        except ValueError:
            raise KeyError(f"skeleton {self.name!r} has no joint {joint_name!r}") from None

    def mirror(self, vectors):
        """(..., J, 3) positions, velocities or bone offsets -> their mirror image: reflected across
        the body's sagittal plane (x -> -x, the left side is +X) with each joint swapped for its
        mirror joint (``symmetry``). An involution; numpy arrays and tensors alike."""
        if not self.symmetry:
            raise ValueError(f"skeleton {self.name!r} has no symmetry: it cannot be mirrored")
        out = vectors[..., list(self.symmetry), :] * 1.0  # a copy, in floating point
        out[..., 0] = -out[..., 0]
        return out

    def children(self, j: int) -> list[int]:
        return [c for c, p in enumerate(self.parents) if p == j]

    def bone_lengths(self, offsets: np.ndarray | None = None) -> np.ndarray:
        """(J,) length of the bone from each joint's parent (0 for the root)."""
        off = self.rest_offsets if offsets is None else offsets
        lengths = np.linalg.norm(off, axis=-1)
        lengths[..., 0] = 0.0
        return lengths

    def rest_positions(self) -> np.ndarray:
        """(J, 3) joint positions in the rest pose."""
        pos = np.zeros((self.num_joints, 3), dtype=np.float32)
        for j, p in enumerate(self.parents):
            pos[j] = self.rest_offsets[j] if p < 0 else pos[p] + self.rest_offsets[j]
        return pos

    def forward_kinematics(
        self,
        rotations: torch.Tensor,  # (..., J, 4) local quaternions
        root_positions: torch.Tensor,  # (..., 3)
        offsets: torch.Tensor | None = None,  # (J, 3) or (..., J, 3); rest offsets if None
    ) -> torch.Tensor:  # (..., J, 3) global joint positions
        if offsets is None:
            offsets = torch.as_tensor(self.rest_offsets, dtype=rotations.dtype, device=rotations.device)
        global_rot = [rotations[..., 0, :]]
        positions = [root_positions]
        for j in range(1, self.num_joints):
            p = self.parents[j]
            positions.append(positions[p] + quat_apply(global_rot[p], offsets[..., j, :]))
            global_rot.append(quat_mul(global_rot[p], rotations[..., j, :]))
        return torch.stack(positions, dim=-2)

    def global_rotations(self, rotations: torch.Tensor) -> torch.Tensor:
        """(..., J, 4) local -> (..., J, 4) global (world-frame) rotations."""
        out = [rotations[..., 0, :]]
        for j in range(1, self.num_joints):
            out.append(quat_mul(out[self.parents[j]], rotations[..., j, :]))
        return torch.stack(out, dim=-2)

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "names": list(self.names),
            "parents": list(self.parents),
            "rest_offsets": self.rest_offsets.tolist(),
        }

    @classmethod
    def from_parents(
        cls,
        name: str,
        parents: list[int],
        offsets: np.ndarray,
        names: list[str] | None = None,
        **groups,
    ) -> Skeleton:
        """A skeleton from any parent list (e.g. a BVH hierarchy); joint groups are optional."""
        names = names or [f"joint{j}" for j in range(len(parents))]
        return cls(name=name, names=tuple(names), parents=tuple(parents), rest_offsets=offsets, **groups)


def _offsets_from_positions(positions: list[list[float]], parents: list[int]) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float32)
    off = pos.copy()
    for j, p in enumerate(parents):
        if p >= 0:
            off[j] = pos[j] - pos[p]
    return off


def body_parts(skeleton: Skeleton) -> dict[str, tuple[int, ...]]:
    """The skeleton's body parts by name, read from its chains, feet and joint names (a chain's own joints are
    those after its first, which belongs to the chain it branches from):

    - ``root``: joint 0, whose features carry the trajectory;
    - ``left_leg`` / ``right_leg``: the chains that hold a joint of ``feet_left`` / ``feet_right``;
    - ``left_arm`` / ``right_arm``: the other chains whose joints are all named ``left...`` / ``right...``;
    - ``torso``: every other joint (spine, neck, head; a joint in no chain goes with its parent's part);
    - the unions ``legs``, ``arms`` and ``upper_body`` (torso and arms).

    Parts no joint falls in are left out (a skeleton without chains has ``root`` and ``torso``); two chains of one
    kind (a quadruped's front and hind legs) make one part."""
    part: dict[int, str] = {0: "root"}
    for chain in skeleton.chains:
        own = [j for j in chain[1:] if j != 0]
        names = [skeleton.names[j].lower() for j in own]
        side = next((s for s in ("left", "right") if names and all(n.startswith(s) for n in names)), None)
        feet = {"left": skeleton.feet_left, "right": skeleton.feet_right}
        leg = next((s for s in ("left", "right") if set(own) & set(feet[s])), None)
        name = f"{leg}_leg" if leg else f"{side}_arm" if side else "torso"
        for j in own:
            part.setdefault(j, name)
    for j, p in enumerate(skeleton.parents):
        part.setdefault(j, part.get(p, "torso"))  # parents come first: theirs is known
    parts = {name: tuple(j for j in range(skeleton.num_joints) if part[j] == name)
             for name in ("root", "torso", "left_arm", "right_arm", "left_leg", "right_leg")}
    for union, members in (("legs", ("left_leg", "right_leg")), ("arms", ("left_arm", "right_arm")),
                           ("upper_body", ("torso", "left_arm", "right_arm"))):
        parts[union] = tuple(sorted(j for m in members for j in parts[m]))
    return {name: joints for name, joints in parts.items() if joints}


SMPL22_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]

# Joint locations of the neutral SMPL body in its rest pose (metres, +X = body's left),
# rounded; the pelvis is lifted so that the soles touch y = 0.
_SMPL22_REST = [
    [0.0000, 0.9500, 0.0000], [0.0695, 0.8591, -0.0043], [-0.0677, 0.8592, -0.0043],
    [-0.0025, 1.0696, -0.0248], [0.1038, 0.4755, 0.0034], [-0.1060, 0.4747, 0.0029],
    [0.0059, 1.2059, -0.0154], [0.0894, 0.0655, -0.0327], [-0.0888, 0.0608, -0.0328],
    [0.0040, 1.2596, 0.0101], [0.1186, 0.0074, 0.0893], [-0.1214, 0.0040, 0.0927],
    [-0.0113, 1.4712, -0.0154], [0.0757, 1.3826, -0.0002], [-0.0775, 1.3817, -0.0045],
    [0.0057, 1.5405, 0.0301], [0.1988, 1.4079, -0.0105], [-0.1911, 1.4095, -0.0129],
    [0.4542, 1.3949, -0.0377], [-0.4593, 1.3940, -0.0404], [0.7163, 1.4072, -0.0419],
    [-0.7229, 1.4128, -0.0399],
]  # fmt: skip

SMPL22 = Skeleton(
    name="smpl22",
    names=(
        "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
        "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
        "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
        "left_wrist", "right_wrist",
    ),  # fmt: skip
    parents=tuple(SMPL22_PARENTS),
    rest_offsets=_offsets_from_positions(_SMPL22_REST, SMPL22_PARENTS),
    chains=((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20)),
    face_joints=(2, 1, 17, 16),
    feet_left=(7, 10),
    feet_right=(8, 11),
    primal_joints=(0, 10, 11, 15, 20, 21, 9),
    end_effectors=(11, 10, 15, 21, 20),
    symmetry=(0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20),
    leg_bone=(5, 8),
)

SMAL35_PARENTS = [-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 6, 11, 12, 13, 6, 15, 0, 17, 18, 19, 0, 21, 22, 23,
                  0, 25, 26, 27, 28, 29, 30, 16, 16, 16]  # fmt: skip


def _smal35_offsets() -> np.ndarray:
    """A medium dog (about 0.55 m at the withers) standing, facing +Z, left side +X."""
    off = np.zeros((35, 3), dtype=np.float32)
    off[0] = (0.0, 0.56, 0.0)  # pelvis above the floor
    off[1] = (0.0, 0.01, 0.06)
    for j in range(2, 7):  # spine .. spine3
        off[j] = (0.0, 0.005, 0.08)
    for side, (a, b, c, d) in ((1.0, (7, 8, 9, 10)), (-1.0, (11, 12, 13, 14))):  # front legs
        off[a] = (side * 0.08, -0.06, 0.03)
        off[b] = (0.0, -0.17, -0.01)
        off[c] = (0.0, -0.18, 0.0)
        off[d] = (0.0, -0.17, 0.03)
    off[15] = (0.0, 0.10, 0.08)  # neck
    off[16] = (0.0, 0.10, 0.06)  # head
    for side, (a, b, c, d) in ((1.0, (17, 18, 19, 20)), (-1.0, (21, 22, 23, 24))):  # hind legs
        off[a] = (side * 0.08, -0.04, -0.03)
        off[b] = (0.0, -0.17, 0.04)
        off[c] = (0.0, -0.18, -0.06)
        off[d] = (0.0, -0.17, 0.02)
    off[25] = (0.0, 0.03, -0.08)  # tail root
    for j in range(26, 32):
        off[j] = (0.0, -0.01, -0.055)
    off[32] = (0.0, -0.04, 0.14)  # mouth
    off[33] = (0.05, 0.06, -0.02)  # ears
    off[34] = (-0.05, 0.06, -0.02)
    return off


SMAL35 = Skeleton(
    name="smal35",
    names=(
        "pelvis", "pelvis0", "spine", "spine0", "spine1", "spine2", "spine3", "LLeg1", "LLeg2",
        "LLeg3", "LFoot", "RLeg1", "RLeg2", "RLeg3", "RFoot", "Neck", "Head", "LLegBack1",
        "LLegBack2", "LLegBack3", "LFootBack", "RLegBack1", "RLegBack2", "RLegBack3", "RFootBack",
        "Tail1", "Tail2", "Tail3", "Tail4", "Tail5", "Tail6", "Tail7", "Mouth", "LEar", "REar",
    ),  # fmt: skip
    parents=tuple(SMAL35_PARENTS),
    rest_offsets=_smal35_offsets(),
    chains=(
        (0, 1, 2, 3, 4, 5, 6, 15, 16, 32), (6, 7, 8, 9, 10), (6, 11, 12, 13, 14), (0, 17, 18, 19, 20),
        (0, 21, 22, 23, 24), (0, 25, 26, 27, 28, 29, 30, 31), (16, 33), (16, 34),
    ),  # fmt: skip
    face_joints=(11, 7, 21, 17),
    # contacts: front paw then hind paw on each side
    feet_left=(10, 20),
    feet_right=(14, 24),
    primal_joints=(0, 20, 24, 16, 10, 14, 6),
    end_effectors=(24, 20, 16, 14, 10),
    symmetry=(0, 1, 2, 3, 4, 5, 6, 11, 12, 13, 14, 7, 8, 9, 10, 15, 16, 21, 22, 23, 24, 17, 18, 19, 20,
              25, 26, 27, 28, 29, 30, 31, 32, 34, 33),  # fmt: skip
    leg_bone=(22, 23),
)

SKELETONS.register("smpl22", SMPL22)
SKELETONS.register("smal35", SMAL35)


def get_skeleton(spec: str | Skeleton) -> Skeleton:
    """A skeleton by registered name, or the skeleton itself."""
    return SKELETONS.get(spec) if isinstance(spec, str) else spec
