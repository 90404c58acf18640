"""Source motion as a model takes it: a user's motion file read, retargeted onto the model's skeleton and
encoded in the representation the model reads (OmniMotionGPT's human smpl22 maa, habit transfer's quadruped
quatvel), or as joint positions (``omg export``'s motions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from omg.errors import UsageError
from omg.motion import Clip, get_representation
from omg.motion.maa import maa_from_positions
from omg.skeleton import Skeleton, get_skeleton


def read_source_motion(path: Path, skeleton: Skeleton, fps: float, joint_map: str | None, what: str
                       ) -> Clip | np.ndarray:
    """The one reader of a user's source motion: a ``.npy`` as its numeric, finite array (the family says which
    shapes it takes), any other motion file (BVH, ASF/AMC, DeepMimic) read and retargeted onto ``skeleton`` at
    ``fps`` (``joint_map``: the file's rig's map, default detected) as a ``Clip``. ``what`` names the input
    in the one-line errors (``--from_motion``, ``SOURCE``; empty: the path alone)."""
    from omg.files import file_problem, read_array

    where = f"{what} {path}" if what else str(path)
    if problem := file_problem(path):
        raise UsageError(f"{where}: {problem}")
    if path.suffix.lower() != ".npy":
        from omg.io.read import read_motion
        from omg.retarget import retarget

        return retarget(read_motion(path, what=what), skeleton, joint_map=joint_map, fps=fps)
    try:
        array = read_array(path, what)
    except (OSError, ValueError) as e:
        raise UsageError(f"{where}: not a readable .npy array ({e})") from None
    if array.dtype.kind not in "biufc":
        raise UsageError(f"{where}: expected a numeric array, got dtype {array.dtype}")
    if not np.isfinite(array).all():  # the model would sample from NaN
        raise UsageError(f"{where}: holds NaN or inf values ({int((~np.isfinite(array)).sum())} of "
                         f"{array.size}); give finite motion")
    return array


def read_positions(path: Path, skeleton: Skeleton, fps: float, representation: str | None = None,
                   what: str = "") -> np.ndarray:
    """Joint positions (T, J, 3) of ``skeleton`` from a motion file: a ``.npy`` of joint positions, or of
    features (T, D) of ``representation`` decoded to them (``omg export``'s ``*.features.npy``); any other
    motion file read and retargeted at ``fps``. ``what`` as ``read_source_motion``'s."""
    motion = read_source_motion(Path(path), skeleton, fps, None, what)
    if isinstance(motion, Clip):
        return motion.positions.astype(np.float32)
    where = f"{what} {path}" if what else str(path)
    if representation is not None:
        try:
            rep = get_representation(representation, skeleton)
        except UsageError as e:
            raise UsageError(f"{where}: {e}") from None
        if motion.ndim != 2 or motion.shape[1] != rep.dim or len(motion) < 1:
            raise UsageError(f"{where}: expected features (T, {rep.dim}) for {rep.name}, got shape {motion.shape}")
        return rep.decode(torch.from_numpy(motion.astype(np.float32))).numpy()
    J = skeleton.num_joints
    if motion.ndim != 3 or motion.shape[1:] != (J, 3) or len(motion) < 1:
        raise UsageError(f"{where}: expected joint positions (T, {J}, 3) for skeleton {skeleton.name!r}, got shape "
                         f"{motion.shape}")
    return motion.astype(np.float32)


def read_human_motion(path: Path, fps: float, joint_map: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A human motion file -> smpl22 maa features (T, 138) and offsets (22, 3) at ``fps``: BVH / ASF-AMC /
    DeepMimic retargeted to smpl22, or a ``.npy`` of joints (T, 22, 3) or features (T, 138) maa or (T, 263)
    humanml3d263 (OmniMotionGPT's source)."""
    from omg.lit.omgpt import HUMAN_SKELETON

    skeleton = get_skeleton(HUMAN_SKELETON)
    motion = read_source_motion(Path(path), skeleton, fps, joint_map, "--from_motion")
    if isinstance(motion, Clip):
        features, meta = get_representation("maa", skeleton).encode(motion)
        return features, np.asarray(meta["offsets"], dtype=np.float32)
    array = motion.astype(np.float32)
    maa_dim = (skeleton.num_joints + 1) * 6
    if array.ndim == 3 and array.shape[1:] == (skeleton.num_joints, 3):
        return maa_from_positions(array, fps)
    if array.ndim == 2 and array.shape[1] == maa_dim:
        return array, skeleton.rest_offsets.astype(np.float32)
    if array.ndim == 2 and array.shape[1] == 263:
        joints = get_representation("humanml3d263", skeleton).decode(torch.from_numpy(array)).numpy()
        return maa_from_positions(joints, fps)
    raise UsageError(f"--from_motion {path}: an array of shape {array.shape}; expected joints (T, 22, 3) or features "
                     f"(T, {maa_dim}) smpl22 maa or (T, 263) humanml3d263")


def read_quadruped(path: Path, rep, fps: float, joint_map: str | None = None) -> dict[str, Any]:
    """A motion file as features of ``rep`` (quatvel): {features (T, D), offsets (J, 3) of the source, root_start
    (3,), category (the source's, or ""), name}. ``.npy``: quatvel features (T, D) or joint positions (T, J, 3) at
    ``fps``; other files are read and retargeted onto the representation's skeleton (habit transfer's source)."""
    skeleton = rep.skeleton
    found = {"offsets": np.asarray(skeleton.rest_offsets, np.float32), "root_start": np.zeros(3, np.float32),
             "category": "", "name": path.name}
    clip = read_source_motion(Path(path), skeleton, fps, joint_map, "SOURCE")
    if not isinstance(clip, Clip):
        array, J, D = clip, skeleton.num_joints, rep.dim
        if array.ndim == 2 and array.shape[1] == D:
            return {**found, "features": array.astype(np.float32)}
        if not (array.ndim == 3 and array.shape[1:] == (J, 3)):
            raise UsageError(f"SOURCE {path}: a .npy source holds quatvel features (T, {D}) or {skeleton.name} joint "
                             f"positions (T, {J}, 3), got shape {array.shape}")
        # the representation solves the rotations (IK)
        clip = Clip(id=path.stem, skeleton=skeleton, fps=fps, positions=array.astype(np.float32))
    if len(clip.positions) < 2:
        raise UsageError(f"SOURCE {path}: {len(clip.positions)} frame(s), need 2 or more")
    features, meta = rep.encode(clip)
    return {**found, "features": features, "offsets": np.asarray(meta["offsets"], np.float32),
            "root_start": np.asarray(meta["root_start"], np.float32), "category": clip.category or ""}
