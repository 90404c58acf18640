"""Source motion as a model takes it: a user's motion file read, retargeted onto the model's skeleton and
encoded in the representation the model reads (OmniMotionGPT's human smpl22 maa, habit transfer's quadruped
quatvel)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from omg.errors import UsageError
from omg.lit.omgpt import HUMAN_SKELETON
from omg.motion import get_representation
from omg.motion.maa import maa_from_positions
from omg.skeleton import get_skeleton


def read_human_motion(path: Path, fps: float, joint_map: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A human motion file -> smpl22 maa features (T, 138) and offsets (22, 3) at ``fps``."""
    from omg.files import file_problem, read_array

    if problem := file_problem(path):
        raise UsageError(f"--from_motion {path}: {problem}")
    skeleton = get_skeleton(HUMAN_SKELETON)
    if path.suffix.lower() != ".npy":
        from omg.io.read import read_motion
        from omg.retarget import retarget

        clip = retarget(read_motion(path, what="--from_motion"), HUMAN_SKELETON, joint_map=joint_map, fps=fps)
        features, meta = get_representation("maa", skeleton).encode(clip)
        return features, np.asarray(meta["offsets"], dtype=np.float32)
    try:
        array = read_array(path, "--from_motion").astype(np.float32)
    except (ValueError, OSError) as e:
        raise UsageError(f"--from_motion {path}: not a readable .npy file ({e})") from None
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
    ``fps``; other files are read and retargeted onto the representation's skeleton."""
    from omg.files import file_problem, read_array
    from omg.motion import Clip

    skeleton = rep.skeleton
    if problem := file_problem(path):
        raise UsageError(f"SOURCE {path}: {problem}")
    found = {"offsets": np.asarray(skeleton.rest_offsets, np.float32), "root_start": np.zeros(3, np.float32),
             "category": "", "name": path.name}
    if path.suffix.lower() == ".npy":
        try:
            array = read_array(path, "SOURCE")
        except (OSError, ValueError) as e:
            raise UsageError(f"SOURCE {path}: not a readable .npy array ({e})") from None
        if array.dtype.kind in "fc" and not np.isfinite(array).all():  # the model would sample from NaN
            raise UsageError(f"SOURCE {path}: holds NaN or inf values ({int((~np.isfinite(array)).sum())} of "
                             f"{array.size}); give finite motion")
        J, D = skeleton.num_joints, rep.dim
        if array.ndim == 2 and array.shape[1] == D:
            return {**found, "features": array.astype(np.float32)}
        if array.ndim == 3 and array.shape[1:] == (J, 3):  # the representation solves the rotations (IK)
            clip = Clip(id=path.stem, skeleton=skeleton, fps=fps, positions=array.astype(np.float32))
        else:
            raise UsageError(f"SOURCE {path}: a .npy source holds quatvel features (T, {D}) or {skeleton.name} joint "
                             f"positions (T, {J}, 3), got shape {array.shape}")
    else:
        from omg.io.read import read_motion
        from omg.retarget import retarget

        clip = retarget(read_motion(path, what="SOURCE"), skeleton, joint_map=joint_map, fps=fps)
    if len(clip.positions) < 2:
        raise UsageError(f"SOURCE {path}: {len(clip.positions)} frame(s), need 2 or more")
    features, meta = rep.encode(clip)
    return {**found, "features": features, "offsets": np.asarray(meta["offsets"], np.float32),
            "root_start": np.asarray(meta["root_start"], np.float32), "category": clip.category or ""}
