"""Joint positions -> local rotations (IK) -> BVH or glTF files and GIF previews (``omg export``);
or, given a user's rig, the motion on that rig (``omg.retarget.onto_rig``).

Generated motions are joint positions; animation tools want a rig with local rotations.
``positions_to_rotations`` solves them for a fixed skeleton: each joint turns the rest
directions of its child bones onto the observed ones, aiming from where forward kinematics
has put the joint so far, so that errors do not accumulate along a chain.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from omg import kinematics
from omg.errors import UsageError
from omg.io.bvh import write_bvh, write_rig_bvh
from omg.io.contacts import clean_foot_contacts
from omg.io.fbx import FbxCharacter
from omg.io.fbx import write_character as write_fbx_character
from omg.io.gltf import write_glb
from omg.io.rig import RigMotion
from omg.kinematics import clip_offsets
from omg.skeleton import Skeleton, get_skeleton

EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def positions_to_rotations(
    skeleton: Skeleton | str,
    positions: np.ndarray,  # (T, J, 3) metres
    offsets: np.ndarray | None = None,  # (J, 3) rest offsets to keep as they are
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # rotations (T, J, 4), root (T, 3), offsets (J, 3)
    """Local joint rotations that reproduce ``positions`` by forward kinematics (float32 arrays);
    the solver is ``omg.kinematics.positions_to_rotations``, aiming from the FK places.

    Without ``offsets`` the bones come from ``omg.kinematics.clip_offsets``, so that FK is exact
    up to the clip's own bone-length jitter.
    """
    skel = get_skeleton(skeleton)
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float64)  # (T, J, 3)
    if pos.ndim != 3 or pos.shape[1:] != (skel.num_joints, 3):
        raise ValueError(f"positions must be (T, {skel.num_joints}, 3) for {skel.name!r}, got {tuple(pos.shape)}")
    off = clip_offsets(skel, pos) if offsets is None else torch.as_tensor(np.asarray(offsets), dtype=torch.float64)
    local = kinematics.positions_to_rotations(skel, pos, off)
    return local.float().numpy(), pos[:, 0].float().numpy(), off.float().numpy()


FORMATS = ("bvh", "glb", "fbx")


def output_format(format: str | None, to_rig: str | Path | None) -> str:
    """``--format`` as given; by default the character's own onto a character (glb onto a glTF one, fbx onto
    an FBX one: the character itself, animated), else bvh. fbx is an FBX character's only (Blender writes it)."""
    suffix = Path(to_rig).suffix.lower() if to_rig is not None else None
    if format == "fbx" and suffix != ".fbx":
        raise UsageError("--format fbx writes an FBX character with the motion added; give --to_rig CHARACTER.fbx "
                         "(motions on a skeleton, a BVH rig or a glTF character are written as bvh or glb)")
    if format is not None:
        return format
    return {".glb": "glb", ".gltf": "glb", ".fbx": "fbx"}.get(suffix, "bvh")


def write_on_rig(path: str | Path, motion: RigMotion, format: str, also: str | Path | None = None) -> Path:
    """A motion on a user's rig (``omg.retarget.onto_rig``'s) as ``format``: bvh the rig's hierarchy; glb a glTF
    character whole with the animation added (``omg.io.gltf``); fbx or glb an FBX character with it added
    (``omg.io.fbx``, through Blender; ``also``: a second file from the same Blender run, the ``.glb`` of an
    ``.fbx``); glb a BVH rig's joints with a skin."""
    if format == "bvh":
        return write_rig_bvh(path, motion)
    if isinstance(motion.character, FbxCharacter):
        return write_fbx_character(Path(path), motion, also)
    if format == "fbx":
        raise UsageError(f"{path}: only an FBX character is written as fbx; {motion.source or motion.name} is none")
    return write_glb(path, motion)


def model_motion(skeleton: Skeleton, rotations: np.ndarray, root: np.ndarray, offsets: np.ndarray, fps: float,
                 name: str = "motion") -> RigMotion:
    """A motion on a model skeleton as a ``RigMotion`` (what the glTF writer takes)."""
    translations = np.broadcast_to(offsets, (len(rotations), skeleton.num_joints, 3)).copy()
    translations[:, 0] = root
    return RigMotion(name=name, names=list(skeleton.names), parents=list(skeleton.parents),
                     offsets=np.asarray(offsets, dtype=np.float64), fps=float(fps),
                     rotations=np.asarray(rotations, dtype=np.float64), translations=translations)  # fmt: skip


def export_motion(
    out_stem: str | Path,
    positions: np.ndarray,  # (T, J, 3) metres, Y up
    skeleton: Skeleton | str,
    fps: float,
    texts: list[str] | None = None,
    preview: bool = True,
    order: str = "ZXY",
    scale: float = 1.0,
    clean_contacts: bool = False,
    rig: RigMotion | None = None,
    joint_map=None,
    format: str = "bvh",
    rotations: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    view: bool = False,
) -> dict:
    """Write ``<stem>.bvh`` (or ``<stem>.glb`` with ``format="glb"``, ``<stem>.fbx`` onto an FBX character) and,
    with ``preview``, ``<stem>.gif``; returns what was written. ``clean_contacts`` pins planted feet first
    (``omg.io.contacts``).

    ``rotations`` = (local quaternions (T, J, 4), root (T, 3), offsets (J, 3)) a model made: written as they
    are on the model skeleton (an IK round trip would change each bone's twist); without them, or with
    ``clean_contacts`` or a ``rig`` (both work from the positions), rotations are solved by IK.

    With ``rig`` (``omg.retarget.read_rig``'s: a BVH rig, a glTF or an FBX character) the motion is written onto
    that rig (``omg.retarget.onto_rig``, with ``joint_map`` or the one its names fit): its hierarchy, names,
    channels and unit (``order`` and ``scale`` are the model skeleton's BVH settings and do not apply), as
    glb or fbx a character whole with the animation added (``write_on_rig``); the preview draws the rig's
    bones. ``view`` onto an FBX character written as fbx: ``<stem>.glb`` of it too (what a page's glTF viewer
    plays), from the same Blender run.
    """
    from omg.io.render import render_gif

    skel = get_skeleton(skeleton)
    if clean_contacts:
        positions = clean_foot_contacts(positions, skel, fps)
    stem = Path(out_stem)
    target = stem.with_name(f"{stem.name}.{format}")
    if rig is not None:
        from omg.retarget import onto_rig

        motion = onto_rig(positions, skel, rig, fps, joint_map)
        motion = replace(motion, name=stem.name)
        glb = stem.with_name(f"{stem.name}.glb") if view and format == "fbx" else None
        report = {format: str(write_on_rig(target, motion, format, glb)), "frames": len(positions),
                  "rig": rig.source or rig.name, **({"glb": str(glb)} if glb is not None else {})}
        drawn, drawn_skel = [motion.positions()], motion.skeleton()
    else:
        given = rotations is not None and not clean_contacts
        rotations, root, offsets = rotations if given else positions_to_rotations(skel, positions)
        fk = skel.forward_kinematics(torch.from_numpy(rotations), torch.from_numpy(root), torch.from_numpy(offsets))
        if format == "bvh":
            written = write_bvh(target, skel, rotations, root, fps, offsets, order, scale)
        else:
            written = write_glb(target, model_motion(skel, rotations, root, offsets, fps, stem.name))
        report = {format: str(written), "frames": len(positions)}
        if not given:  # a model's rotations are the motion itself: there is no solve to measure
            report["ik_error_m"] = float(np.abs(fk.numpy() - positions).max())
        drawn, drawn_skel = [fk.numpy()], skel
    if preview:
        title = " / ".join(texts) if texts else stem.name
        report["gif"] = str(render_gif(stem.with_name(f"{stem.name}.gif"), drawn, drawn_skel, fps, titles=[title]))
    return report
