"""The ``aistpp`` source: AIST++ dance motion (SMPL parameters) -> smpl22 clips.

Input (``--input``): the ``motions/`` folder of the AIST++ annotations (or any folder below
which ``*.pkl`` files lie), one pickle per sequence, named like
``gBR_sBM_cAll_d04_mBR0_ch01.pkl``, each a dict with

- ``smpl_poses`` (T, 72): SMPL axis-angle rotations, joint 0 the global orientation;
- ``smpl_trans`` (T, 3): the root translation in the capture's centimetres, i.e. multiplied
  by ``smpl_scaling``;
- ``smpl_scaling`` (1,): the body's scale in that frame (about 90-100);
- ``smpl_loss`` (ignored).

AIST++ is Y-up at 60 fps. As AIST++'s own API does, the body is SMPL with zero shape and the
translation ``smpl_trans / smpl_scaling`` (metres at the SMPL body's size); the sequence is
then retargeted onto smpl22 as ``omg.data.sources.smpl`` describes (resampled to ``--fps``,
floor under the planted feet). Sequences named in an ``ignore_list.txt`` (one name per line,
as the annotations ship it beside ``motions/``) in the input folder or its parent are passed
over. Clips are unlabeled (no captions); ``labels`` hold the dance genre, the situation
(basic / advanced), the dancer and the music from the file name.

Options: ``body_model`` (required; an SMPL ``model.npz`` or a folder with
``{male,female,neutral}/model.npz`` as for ``amass``: AIST++ fits use the neutral body unless
``gender`` says otherwise), ``gender`` (default neutral), ``source_fps`` (default 60, AIST++'s
rate), ``up`` (default ``y``). The pickles are read with an unpickler that accepts only numpy
arrays, so a file cannot run code. A file that cannot be read or lacks a key is one counted skip.
"""

from __future__ import annotations

import io
import pickle
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
from omg.files import MOTION_MAX_BYTES, TEXT_MAX_BYTES, read_file
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.skeleton import Skeleton

AISTPP_FPS = 60.0  # AIST++ motions are at 60 fps (Li et al. 2021, "AI Choreographer", Sec. 3)
GENRES = {"gBR": "break", "gPO": "pop", "gLO": "lock", "gMH": "middle hip-hop", "gLH": "LA-style hip-hop",
          "gHO": "house", "gWA": "waack", "gKR": "krump", "gJS": "street jazz", "gJB": "ballet jazz"}
SITUATIONS = {"sBM": "basic", "sFM": "advanced"}


class _ArraysOnly(pickle.Unpickler):
    """Unpickles dicts, lists and numpy arrays only: a motion file must not run code."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "scalar"),
               ("numpy._core.multiarray", "scalar")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refuses {module}.{name}: only numpy arrays are read")
        return super().find_class(module, name)


def read_pickle(path: Path) -> dict:
    # read_file: a FIFO cannot block, a huge file is refused (AIST++'s pickles are ~1 MB)
    data = _ArraysOnly(io.BytesIO(read_file(path, "", MOTION_MAX_BYTES)), encoding="latin1").load()
    if not isinstance(data, dict):
        raise ValueError(f"a {type(data).__name__}, not a dict")
    return data


def labels_from_name(stem: str) -> dict:
    """``gBR_sBM_cAll_d04_mBR0_ch01`` -> genre, situation, dancer, music (what the name holds)."""
    labels = {}
    for part in stem.split("_"):
        if part in GENRES:
            labels["genre"] = GENRES[part]
        elif part in SITUATIONS:
            labels["situation"] = SITUATIONS[part]
        elif part.startswith("d") and part[1:].isdigit():
            labels["dancer"] = part
        elif part.startswith("m") and part[1:3] in {g[1:] for g in GENRES}:
            labels["music"] = part
    return labels


def _load(root: Path, path: Path, body_model: Path, gender: str, skeleton: Skeleton, fps: float, source_fps: float,
          up: str) -> Clip | Exception:
    try:
        try:
            data = read_pickle(path)
        except Exception as e:  # noqa: BLE001 - any unreadable file is one counted skip
            raise ValueError(f"aistpp unreadable file: {path} ({type(e).__name__}: {e})") from None
        if missing := [k for k in ("smpl_poses", "smpl_trans", "smpl_scaling") if k not in data]:
            raise ValueError(f"aistpp missing keys: {path} lacks {', '.join(missing)}")
        poses = np.asarray(data["smpl_poses"], dtype=np.float64)
        scaling = np.asarray(data["smpl_scaling"], dtype=np.float64).reshape(-1)
        if len(scaling) != 1 or not np.isfinite(scaling).all() or scaling[0] <= 0:
            raise ValueError(f"aistpp bad smpl_scaling: {path} has {data['smpl_scaling']!r}, expected one number > 0")
        trans = np.asarray(data["smpl_trans"], dtype=np.float64) / scaling[0]  # centimetres at scale -> metres
        check_sequence(f"aistpp bad motion: {path}", poses, trans)
        model = body_model_for(body_model, gender)
        rel = path.relative_to(root).with_suffix("")
        motion = rig_motion(model, poses, trans, np.zeros(0), source_fps, rel.name, str(path))
        return smpl_clip(motion, skeleton, fps, up, rel.as_posix(), labels_from_name(rel.name), [], str(path))
    except ValueError as e:
        if isinstance(e, UsageError):
            raise
        return e


def ignored(root: Path) -> set[str]:
    """Sequence names AIST++'s ``ignore_list.txt`` (in the folder or its parent) lists."""
    for folder in (root, root.parent):
        if (folder / "ignore_list.txt").exists():  # a FIFO or a huge one: one line, not a hang
            data = read_file(folder / "ignore_list.txt", "aistpp:", TEXT_MAX_BYTES)
            lines = data.decode("utf-8", errors="replace").splitlines()
            return {line.strip() for line in lines if line.strip()}
    return set()


@DATA_SOURCES.register("aistpp")
def aistpp_source(input: str | None, skeleton: Skeleton, fps: float, body_model: str | None = None,
                  gender: str = "neutral", source_fps: float = AISTPP_FPS, up: str = "y") -> list[LazyItem]:
    """Unlabeled smpl22 dance clips from AIST++ SMPL pickles; see the module docstring."""
    if not input or not Path(input).is_dir():
        raise UsageError(f"aistpp: --input must be a folder of AIST++ .pkl motions (motions/), got {input!r}")
    model_path = check_body_model("aistpp", body_model, skeleton)
    check_sequence_options("aistpp", up, source_fps)
    root = Path(input)
    skip = ignored(root)
    paths = [p for p in sorted(root.rglob("*.pkl")) if p.stem not in skip]
    return [LazyItem(_load, (root, p, model_path, gender, skeleton, fps, float(source_fps), up)) for p in paths]
