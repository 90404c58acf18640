"""The ``motionx`` source: Motion-X (SMPL-X) motion -> smpl22 clips, body joints only.

Input (``--input``): Motion-X's dataset folder or any folder below which the motion files lie.
Where it holds ``motion_data/smplx_322/`` (Motion-X's release layout), the motions are read
from there and each clip's captions from ``texts/semantic_labels/<same path>.txt`` (one
caption per line) when that file exists. Two file kinds, searched recursively:

- ``*.npy``: Motion-X's (T, 322) SMPL-X frames: ``[0:3]`` root orientation, ``[3:66]`` body
  pose (21 joints), ``[66:156]`` hands, ``[156:159]`` jaw, ``[159:209]`` face expression,
  ``[209:309]`` face shape, ``[309:312]`` translation, ``[312:322]`` betas (static), as the
  Motion-X README lays them out; 30 fps (Motion-X unifies every subset to 30 fps) and Y up;
- ``*.npz``: SMPL-X parameter files (AMASS SMPL-X, Motion-X's mocap subsets before packing):
  ``root_orient`` (T, 3) + ``pose_body`` (T, 63), or ``poses`` (T, >=66); ``trans`` (T, 3);
  optional ``betas``, ``gender`` and ``mocap_frame_rate`` / ``mocap_framerate`` / ``fps``.

Hands, jaw, eyes and face are dropped: a clip is the first 22 SMPL-X joints (SMPL's body
joints), posed by the body model (``--option.body_model``: an SMPL-X ``model.npz`` with
``v_template``, ``shapedirs``, ``J_regressor``, ``kintree_table``, or a folder of
``{male,female,neutral}/model.npz``; expression blend shapes are ignored, they move face
vertices only), then retargeted onto smpl22 as ``omg.data.sources.smpl`` describes. The id is
the path relative to the motion folder without its suffix; ``labels`` hold the subset (the
first folder) and the gender.

Options: ``body_model`` (required), ``source_fps`` (default 30: the rate of ``.npy`` files and
of ``.npz`` files that record none), ``up`` (default ``y``; ``z`` for Z-up AMASS ``.npz``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omg.data.shards import LazyItem
from omg.data.sources.smpl import (
    body_model_for,
    check_body_model,
    check_sequence,
    check_sequence_options,
    rig_motion,
    smpl_clip,
)
from omg.errors import UsageError
from omg.files import TEXT_MAX_BYTES, read_array, read_file
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.skeleton import Skeleton

MOTIONX_FPS = 30.0  # "All motions have been unified in 30 fps" (Motion-X README, Lin et al. 2023)
MOTIONX_DIM = 322
ROOT, BODY, TRANS, BETAS = slice(0, 3), slice(3, 66), slice(309, 312), slice(312, 322)  # the README's layout
RATE_KEYS = ("mocap_frame_rate", "mocap_framerate", "fps")


def _read(path: Path, source_fps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, str, float]:
    """(T, 66) body poses, (T, 3) trans, betas, gender, fps of one file; ValueError when unusable."""
    try:
        if path.suffix == ".npy":
            frames = read_array(path, "")
            data = None
        else:
            with read_array(path, "") as f:
                data = {k: f[k] for k in f.files}
    except Exception as e:  # noqa: BLE001 - any unreadable file (a FIFO, a huge file too) is one counted skip
        raise ValueError(f"motionx unreadable file: {path} ({type(e).__name__}: {e})") from None
    if data is None:
        if frames.ndim != 2 or frames.shape[1] != MOTIONX_DIM:
            raise ValueError(f"motionx wrong array shape: {path} is {frames.shape}, Motion-X frames are "
                             f"(T, {MOTIONX_DIM})")
        frames = frames.astype(np.float64)
        poses = np.concatenate([frames[:, ROOT], frames[:, BODY]], axis=1)
        return poses, frames[:, TRANS], frames[0, BETAS], "neutral", source_fps
    if "root_orient" in data and "pose_body" in data:
        poses = np.concatenate([np.asarray(data["root_orient"]).reshape(len(data["root_orient"]), -1),
                                np.asarray(data["pose_body"]).reshape(len(data["pose_body"]), -1)], axis=1)
    elif "poses" in data:
        poses = np.asarray(data["poses"])
    else:
        raise ValueError(f"motionx missing keys: {path} lacks root_orient + pose_body (or poses)")
    if "trans" not in data:
        raise ValueError(f"motionx missing keys: {path} lacks trans")
    rate_key = next((k for k in RATE_KEYS if k in data), None)
    rate = float(np.asarray(data[rate_key]).reshape(-1)[0]) if rate_key else source_fps
    if not np.isfinite(rate) or rate <= 0:
        raise ValueError(f"motionx bad frame rate: {path} has {rate_key} {rate}")
    gender = np.asarray(data.get("gender", "neutral")).reshape(-1)[0]
    gender = gender.decode() if isinstance(gender, bytes) else str(gender)
    betas = np.asarray(data.get("betas", np.zeros(0)), dtype=np.float64).reshape(-1)
    return poses.astype(np.float64), np.asarray(data["trans"], dtype=np.float64), betas, gender, rate


def _captions(texts: Path | None, rel: Path) -> list[str]:
    if texts is None or not (path := texts / rel.with_suffix(".txt")).exists():
        return []
    try:
        lines = read_file(path, "", TEXT_MAX_BYTES).decode("utf-8", errors="replace").splitlines()
    except UsageError as e:  # a FIFO or a huge file: the clip is a counted skip, not the build's end
        raise ValueError(f"motionx unreadable file: {path} ({type(e).__name__}: {e})") from None
    return [line.strip() for line in lines if line.strip()]


def _load(root: Path, path: Path, texts: Path | None, body_model: Path, skeleton: Skeleton, fps: float,
          source_fps: float, up: str) -> Clip | Exception:
    try:
        poses, trans, betas, gender, rate = _read(path, source_fps)
        check_sequence(f"motionx bad motion: {path}", poses, trans)
        rel = path.relative_to(root)
        model = body_model_for(body_model, gender)
        motion = rig_motion(model, poses, trans, betas, rate, rel.stem, str(path))
        labels = {"subset": rel.parts[0] if len(rel.parts) > 1 else "", "gender": gender}
        return smpl_clip(motion, skeleton, fps, up, rel.with_suffix("").as_posix(), labels, _captions(texts, rel),
                         str(path))
    except ValueError as e:
        if isinstance(e, UsageError):
            raise
        return e


@DATA_SOURCES.register("motionx")
def motionx_source(input: str | None, skeleton: Skeleton, fps: float, body_model: str | None = None,
                   source_fps: float = MOTIONX_FPS, up: str = "y") -> list[LazyItem]:
    """smpl22 body clips from Motion-X SMPL-X .npy (and SMPL-X .npz) files; see the module docstring."""
    if not input or not Path(input).is_dir():
        raise UsageError(f"motionx: --input must be a folder of Motion-X .npy / SMPL-X .npz files, got {input!r}")
    model_path = check_body_model("motionx", body_model, skeleton)
    check_sequence_options("motionx", up, source_fps)
    root, texts = Path(input), None
    if (root / "motion_data" / "smplx_322").is_dir():  # Motion-X's release layout
        root, texts = root / "motion_data" / "smplx_322", root / "texts" / "semantic_labels"
    # not is_file(): a FIFO or device named like a motion is listed, then a counted skip when read
    paths = sorted(p for p in root.rglob("*") if p.suffix in (".npy", ".npz") and not p.is_dir())
    return [LazyItem(_load, (root, p, texts, model_path, skeleton, fps, float(source_fps), up)) for p in paths]
