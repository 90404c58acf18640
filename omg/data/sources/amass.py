"""The ``amass`` source: AMASS SMPL / SMPL-H parameter files -> smpl22 joint positions.

Input (``--input``): a folder searched recursively for AMASS ``.npz`` files, each with
``poses`` (T, 156) for SMPL-H or (T, 72) for SMPL (axis-angle, joint 0 = global orientation),
``trans`` (T, 3), ``betas`` (10 or 16), ``mocap_framerate`` (or ``mocap_frame_rate``) and
``gender``. Per-subject ``shape.npz`` files (betas only) are ignored.

Option ``body_model`` (required): the SMPL / SMPL-H body model as ``.npz`` with
``v_template`` (V, 3), ``shapedirs`` (V, 3, B), ``J_regressor`` (J, V) and ``kintree_table``
(2, J), as shipped in AMASS's ``body_models/smplh/<gender>/model.npz``; or a folder with
``male/model.npz``, ``female/model.npz`` and ``neutral/model.npz``, picked by each file's
gender (neutral when the gender's model is absent). The ``.pkl`` models need chumpy:
convert them to ``.npz`` first.

Joints: ``J = J_regressor @ (v_template + shapedirs @ betas)``, forward kinematics with the
first 22 joints' rotations (SMPL's joint order and parents are smpl22's), plus ``trans``;
then AMASS's Z-up turns Y-up as HumanML3D's ``raw_pose_processing`` does ((x, y, z) ->
(-x, z, y)), and the sequence is resampled to ``--fps`` by linear interpolation (which picks
every n-th frame when the rates divide, e.g. 120 -> 20 fps). Clips are unlabeled
(``texts`` empty, ``category`` human); ``labels`` hold the dataset folder and the gender.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omg.data.shards import LazyItem
from omg.data.sources.smpl import NUM_JOINTS, BodyModel, body_model_for, check_body_model
from omg.errors import UsageError
from omg.files import read_array
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.rotations import axis_angle_to_quat, quat_to_matrix
from omg.skeleton import SMPL22_PARENTS, Skeleton

Z_UP_TO_Y_UP = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])  # new = M @ old: (-x, z, y)


def smpl_joints(model: BodyModel, poses: np.ndarray, trans: np.ndarray, betas: np.ndarray) -> np.ndarray:
    """(T, >=66) axis-angle poses, (T, 3) trans, betas -> (T, 22, 3) joints in the model's frame."""
    rest = model.rest_joints(betas)  # (22, 3)
    aa = torch.from_numpy(poses[:, : NUM_JOINTS * 3].reshape(len(poses), NUM_JOINTS, 3))
    R = quat_to_matrix(axis_angle_to_quat(aa)).numpy()  # (T, 22, 3, 3) local rotations
    G = [R[:, 0]]
    joints = [np.broadcast_to(rest[0], (len(poses), 3)) + trans]
    for j in range(1, NUM_JOINTS):
        p = SMPL22_PARENTS[j]
        joints.append(joints[p] + G[p] @ (rest[j] - rest[p]))
        G.append(G[p] @ R[:, j])
    return np.stack(joints, axis=1)


def resample(x: np.ndarray, src_fps: float, dst_fps: float) -> np.ndarray:
    """(T, ...) at src_fps -> (T', ...) at dst_fps over the same duration, linear in time."""
    t = np.arange(0.0, (len(x) - 1) / src_fps + 1e-9, 1.0 / dst_fps) * src_fps  # source frame indices
    i = np.minimum(np.floor(t + 1e-6).astype(int), len(x) - 1)
    w = np.clip(t - i, 0.0, 1.0).reshape(-1, *[1] * (x.ndim - 1))
    return (1 - w) * x[i] + w * x[np.minimum(i + 1, len(x) - 1)]


def _read_clip(root: Path, path: Path, body_model: Path, skeleton: Skeleton, fps: float) -> Clip | None:
    try:
        with read_array(path, "") as f:  # (T, 156) float64 poses, 1.2 KiB a frame: the bound holds 30 min at 120 fps
            data = {k: f[k] for k in f.files}
    except Exception as e:  # noqa: BLE001 - any unreadable file (a FIFO, a huge file too) is one counted skip
        raise ValueError(f"amass unreadable file: {path} ({type(e).__name__}: {e})") from None
    if "poses" not in data and path.name == "shape.npz":
        return None
    rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in data), None)
    if missing := [k for k in ("poses", "trans", "betas") if k not in data] + ([] if rate_key else ["mocap_framerate"]):
        raise ValueError(f"amass missing keys: {path} lacks {', '.join(missing)}")
    poses, trans = data["poses"].astype(np.float64), data["trans"].astype(np.float64)
    if poses.ndim != 2 or poses.shape[1] < NUM_JOINTS * 3 or trans.shape != (len(poses), 3) or len(poses) < 2:
        raise ValueError(f"amass wrong array shape: {path} has poses {poses.shape}, trans {trans.shape}")
    if not (np.isfinite(poses).all() and np.isfinite(trans).all()):
        raise ValueError(f"amass NaN or inf in motion: {path}")
    gender = np.asarray(data.get("gender", "neutral")).reshape(-1)[0]
    gender = gender.decode() if isinstance(gender, bytes) else str(gender)
    model = body_model_for(body_model, gender)
    joints = smpl_joints(model, poses, trans, data["betas"].astype(np.float64).reshape(-1))
    joints = resample(joints @ Z_UP_TO_Y_UP.T, float(data[rate_key]), fps)
    rel = path.relative_to(root).with_suffix("")
    return Clip(
        id=rel.as_posix(),
        skeleton=skeleton,
        fps=fps,
        positions=joints.astype(np.float32),
        labels={"dataset": rel.parts[0] if len(rel.parts) > 1 else "", "gender": gender},
        category="human",
        source="amass",
    )


@DATA_SOURCES.register("amass")
def amass_source(input: str | None, skeleton: Skeleton, fps: float,
                 body_model: str | None = None) -> list[LazyItem]:
    """Unlabeled smpl22 clips from AMASS .npz files; see the module docstring."""
    if not input or not Path(input).is_dir():
        raise UsageError(f"amass: --input must be a folder of AMASS .npz files, got {input!r}")
    model_path = check_body_model("amass", body_model, skeleton)
    root = Path(input)
    return [LazyItem(_load_clip, (root, path, model_path, skeleton, fps)) for path in sorted(root.rglob("*.npz"))]


def _load_clip(root: Path, path: Path, body_model: Path, skeleton: Skeleton, fps: float) -> Clip | Exception | None:
    """One file, read when the build gets to it (in a helper process with --workers)."""
    try:
        return _read_clip(root, path, body_model, skeleton, fps)
    except UsageError:  # a bad body model is the user's to fix, not a bad clip
        raise
    except ValueError as e:
        return e
