"""The ``humanml3d`` source: a HumanML3D release folder (Guo et al. 2022) on smpl22 at 20 fps.

Expected layout under ``--input`` (as the HumanML3D scripts write it)::

    new_joint_vecs/<id>.npy   (T - 1, 263) float features       } at least one of the two
    new_joints/<id>.npy       (T, 22, 3) canonical joint positions }
    texts/<id>.txt            one caption per line: ``caption#word/POS word/POS ...#start#end``
    train.txt val.txt test.txt  (optional) one id per line; option ``split`` picks one
    Mean.npy Std.npy          (optional) (263,) the published normalisation

Options: ``split`` (``train``, ``val``, ``test``, ``train_val`` or ``all``; default ``all``,
which reads every id in ``new_joint_vecs``/``new_joints``), ``min_frames`` and
``max_frames`` (default 20 and 196, both kept: the papers' HumanML3D filter keeps clips with
``20 <= frames <= 196`` feature frames; set ``max_frames=0`` to keep long clips).

As in HumanML3D's ``Text2MotionDataset``: a caption whose start/end (seconds) are not both
zero describes the span ``[int(start * 20), int(end * 20))`` of the motion and becomes its
own sub-clip (id ``<id>@<start>-<end>``; captions sharing a span share the sub-clip); the
other captions stay with the whole clip, which is kept only if it has at least one. Each
caption's word/POS tokens travel in ``labels["tokens"]`` (one list per caption, aligned with
``texts``), since T2M's evaluator needs them.

``new_joint_vecs`` are carried as precomputed ``humanml3d263`` features, so shards of that
representation hold the published numbers verbatim, and ``Mean.npy``/``Std.npy`` become the
manifest's mean/std. Positions come from ``new_joints`` when present, else from decoding the
features (``recover_from_ric``). Files with NaN (e.g. 007975) or of the wrong shape are
yielded as errors: skipped and counted by reason, with the file in the message.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from omg.data.shards import SourceItems
from omg.errors import UsageError
from omg.files import read_array, read_text
from omg.motion import Clip, get_representation
from omg.registry import DATA_SOURCES
from omg.skeleton import Skeleton

FPS = 20.0  # HumanML3D's frame rate; caption spans are in seconds at this rate
SPLITS = ("train", "val", "test", "train_val", "all")


def parse_caption_line(line: str) -> tuple[str, list[str], float, float]:
    """``caption#tokens#start#end`` -> (caption, tokens, start, end); NaN spans read as 0."""
    parts = line.strip().split("#")
    if len(parts) < 4:
        raise ValueError(f"expected caption#tokens#start#end, got {line.strip()!r}")
    start, end = float(parts[2]), float(parts[3])
    start = 0.0 if np.isnan(start) else start
    end = 0.0 if np.isnan(end) else end
    return parts[0], parts[1].split(" ") if parts[1] else [], start, end


def _split_ids(root: Path, split: str) -> list[str]:
    if split not in SPLITS:
        raise UsageError(f"humanml3d: --option.split {split!r}; choose from {', '.join(SPLITS)}")
    if split == "all":
        ids = {p.stem for d in ("new_joint_vecs", "new_joints") for p in (root / d).glob("*.npy")}
        return sorted(ids)
    path = root / f"{split}.txt"
    if not path.exists() and not path.is_symlink():
        raise UsageError(f"humanml3d: split file {path} not found; use --option.split all to read every clip")
    return [line.strip() for line in read_text(path, "humanml3d: split file").splitlines() if line.strip()]


def _load(path: Path, shape: tuple) -> np.ndarray:
    """Load an .npy whose trailing dims must equal ``shape``; ValueError names the reason and file."""
    try:
        array = read_array(path, "")  # a FIFO or a huge file too: a UsageError, caught here
    except Exception as e:  # noqa: BLE001 - any unreadable file is one counted skip
        raise ValueError(f"humanml3d unreadable file: {path} ({type(e).__name__}: {e})") from None
    if array.ndim != len(shape) + 1 or array.shape[1:] != shape:
        raise ValueError(f"humanml3d wrong array shape: {path} is {array.shape}, "
                         f"expected (T, {', '.join(map(str, shape))})")
    if not np.isfinite(array).all():
        raise ValueError(f"humanml3d NaN or inf in motion: {path}")
    return array.astype(np.float32)


def _published_stat(path: Path) -> np.ndarray:
    """Mean.npy or Std.npy: 263 numbers (never unpickled: an object array could run code as it is read)."""
    try:
        array = read_array(path, "humanml3d:")
    except UsageError:  # no regular file, or too large: read_file's one line
        raise
    except (OSError, ValueError, EOFError) as e:
        raise UsageError(f"humanml3d: {path} is not a plain numeric .npy array ({' '.join(str(e).split())[:120]}); "
                         "remove it or use the published file") from None
    if array.shape != (263,) or not np.issubdtype(array.dtype, np.number) or not np.isfinite(array).all():
        raise UsageError(f"humanml3d: {path} holds {array.shape} {array.dtype} values, expected 263 finite numbers; "
                         "remove it or use the published file")
    return array


def _read_clips(root: Path, name: str, skeleton: Skeleton, min_frames: int,
                max_frames: int) -> Iterator[Clip | Exception]:
    vec_path, joint_path = root / "new_joint_vecs" / f"{name}.npy", root / "new_joints" / f"{name}.npy"
    text_path = root / "texts" / f"{name}.txt"
    try:
        features = _load(vec_path, (263,)) if vec_path.exists() else None  # (T - 1, 263)
        joints = _load(joint_path, (22, 3)) if joint_path.exists() else None  # (T, 22, 3)
        if features is None and joints is None:
            raise ValueError(f"humanml3d missing motion: neither {vec_path} nor {joint_path} exists")
        if not text_path.exists():
            raise ValueError(f"humanml3d missing captions: {text_path}")
        spans: dict[tuple[float, float], list[tuple[str, list[str]]]] = defaultdict(list)
        try:
            text = read_text(text_path, "")
        except UsageError as e:  # a FIFO, a huge or non-UTF-8 file: one counted skip, as an unreadable motion
            raise ValueError(f"humanml3d unreadable file: {text_path} ({type(e).__name__}: {e})") from None
        for i, line in enumerate(text.splitlines()):
            if line.strip():
                try:
                    caption, tokens, start, end = parse_caption_line(line)
                except ValueError as e:
                    raise ValueError(f"humanml3d bad caption line: {text_path}:{i + 1} {e}") from None
                spans[(start, end)].append((caption, tokens))
    except ValueError as e:
        yield e
        return
    frames = len(features) if features is not None else len(joints) - 1  # feature frames (T - 1)
    motion_path = vec_path if features is not None else joint_path

    def bad_length(length: int) -> bool:
        return length < min_frames or bool(max_frames and length > max_frames)

    # as in HumanML3D's loader, the whole motion must pass the length filter, sub-clips too
    if bad_length(frames):
        yield ValueError(f"humanml3d length outside [{min_frames}, {max_frames or 'inf'}] frames: "
                         f"{motion_path} has {frames}")
        return
    for (start, end), captions in sorted(spans.items()):
        whole = start == 0.0 and end == 0.0
        a, b = (0, frames) if whole else (int(start * FPS), min(int(end * FPS), frames))
        clip_id = name if whole else f"{name}@{start:g}-{end:g}"
        if bad_length(b - a):
            yield ValueError(f"humanml3d length outside [{min_frames}, {max_frames or 'inf'}] frames: "
                             f"{clip_id} has {b - a} ({motion_path})")
            continue
        if features is not None:
            clip_features = features[a:b]  # the published crop: HumanML3D slices the feature rows
            if joints is not None and len(joints) == frames + 1:
                positions = joints[a : b + 1]  # (length + 1, 22, 3): features drop the last frame
            else:  # recover_from_ric: one position row per feature row
                rep = get_representation("humanml3d263", skeleton)
                positions = rep.decode(torch.from_numpy(clip_features)).numpy()
        else:
            clip_features, positions = None, joints[a : b + 1]
        yield Clip(
            id=clip_id,
            skeleton=skeleton,
            fps=FPS,
            positions=np.ascontiguousarray(positions, dtype=np.float32),
            texts=[c for c, _ in captions],
            labels={"tokens": [t for _, t in captions], "humanml3d_id": name, "span": [start, end]},
            category="human",
            source="humanml3d",
            features=clip_features,
            features_representation=None if clip_features is None else "humanml3d263",
        )


@DATA_SOURCES.register("humanml3d")
def humanml3d_source(
    input: str | None,
    skeleton: Skeleton,
    fps: float,
    split: str = "all",
    min_frames: int = 20,
    max_frames: int = 196,
) -> SourceItems:
    """Clips (and sub-clips per captioned span) of a HumanML3D folder; see the module docstring."""
    if not input or not Path(input).is_dir():
        raise UsageError("humanml3d: --input must be a HumanML3D folder (with new_joint_vecs/ and texts/), "
                         f"got {input!r}")
    if skeleton.name != "smpl22":
        raise UsageError(f"humanml3d motion is on smpl22, not {skeleton.name!r}; use --skeleton smpl22")
    if abs(fps - FPS) > 1e-6:
        raise UsageError(f"humanml3d motion is at {FPS:g} fps; use --fps {FPS:g}")
    root = Path(input)
    ids = _split_ids(root, split)
    stats = {}
    if (root / "Mean.npy").exists() and (root / "Std.npy").exists():
        stats["humanml3d263"] = (_published_stat(root / "Mean.npy"), _published_stat(root / "Std.npy"))

    def items() -> Iterator[Clip | Exception]:
        for name in ids:
            yield from _read_clips(root, name, skeleton, min_frames, max_frames)

    return SourceItems(items(), stats)
