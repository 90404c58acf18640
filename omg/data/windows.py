"""What a training sample is cut from a clip, and the pad + mask collate.

Two ways to cut, chosen by what the model learns from:

- ``windows`` (unlabeled pretraining, OMG Sec. 3.1): sliding random windows, a length
  l ~ U[min_len, min(L, T)] and a start i ~ U[0, T - l]. The paper's l ~ U[1, L] ("even a single
  keyframe") is the default (``min_len`` 1; L = 300 frames at 30 fps in the pretraining configs);
  ``min_len`` 60 gives omg's earlier U[60, L]. A long take yields proportionally more windows than
  a short clip (``visits``), so every frame of the data is equally likely to be trained on. Clips
  shorter than ``min_len`` are used whole.
- ``whole`` (captioned data: a caption describes its whole clip): the clip itself, cropped at
  a random start to ``max_len`` only when longer, as HumanML3D's loaders do (196 frames);
  clips shorter than ``min_len`` are not trained on (the papers' length filters: HumanML3D
  20, AnimalML3D 10 frames), whatever bounds the shards were built with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from omg.errors import UsageError
from omg.motion import length_mask
from omg.text.sides import mirror_caption

CLIP_MODES = ("windows", "whole")
# the shortest sample of each mode when data.min_len is not given: a window may be a single frame
# (OMG Sec. 3.1: l ~ U[1, L]); a whole captioned clip needs 40 (HumanML3D's loader, min_motion_len)
DEFAULT_MIN_LEN = {"windows": 1, "whole": 40}


@dataclass(frozen=True)
class WindowSampler:
    max_len: int = 300
    min_len: int | None = None  # None: DEFAULT_MIN_LEN of the mode
    mode: str = "windows"  # one of CLIP_MODES

    def __post_init__(self):
        if self.mode not in CLIP_MODES:
            raise UsageError(f"data.clips must be one of {', '.join(CLIP_MODES)}, got {self.mode!r}")
        if self.min_len is None:
            object.__setattr__(self, "min_len", min(DEFAULT_MIN_LEN[self.mode], self.max_len))
        if not 1 <= self.min_len <= self.max_len:
            raise UsageError("windows need 1 <= min_len <= max_len, "
                             f"got min_len={self.min_len}, max_len={self.max_len}")

    def __call__(self, num_frames: int, rng: np.random.Generator) -> tuple[int, int]:
        """(start, length) of the next training sample of a clip, by ``mode``."""
        return self.random(num_frames, rng) if self.mode == "windows" else self.whole(num_frames, rng)

    def random(self, num_frames: int, rng: np.random.Generator) -> tuple[int, int]:
        """(start, length) of a random window."""
        high = min(self.max_len, num_frames)
        low = min(self.min_len, high)
        length = int(rng.integers(low, high + 1))
        start = int(rng.integers(0, num_frames - length + 1))
        return start, length

    def keeps(self, num_frames: int) -> bool:
        """Whether a clip is trained on: a whole clip needs ``min_len`` frames; windows use a short clip whole."""
        return self.mode == "windows" or num_frames >= self.min_len

    def whole(self, num_frames: int, rng: np.random.Generator) -> tuple[int, int]:
        """(start, length): the whole clip, or a random ``max_len`` crop of a longer one."""
        length = min(self.max_len, num_frames)
        return int(rng.integers(0, num_frames - length + 1)), length

    def visits(self, num_frames: int, mean_frames: float | None, rng: np.random.Generator) -> int:
        """How many samples a clip yields when the stream reads it.

        ``whole`` clips and streams without a ``mean_frames`` yield one per read. Sliding windows
        yield T / mean_frames on average (random rounding of the fraction), so over a pass of
        the data a clip contributes in proportion to its frames and a set of average clips
        still yields one window per clip read; a clip may then yield none on a given read.
        """
        if self.mode == "whole" or not mean_frames:
            return 1
        expected = num_frames / mean_frames
        whole = int(expected)
        return whole + int(rng.random() < expected - whole)

    def center(self, num_frames: int) -> tuple[int, int]:
        """The deterministic window used for validation: the middle ``max_len`` frames."""
        length = min(self.max_len, num_frames)
        return (num_frames - length) // 2, length


def make_item(sample: dict, start: int, length: int, text: str) -> dict:
    """Cut a decoded sample to a window; ``text`` is the caption chosen for this visit."""
    meta = sample["meta"]
    item = {
        "motion": sample["motion"][start : start + length],  # (l, D)
        "text": text,
        "id": meta["id"],
        "category": meta.get("category") or "",
        "labels": meta.get("labels") or {},
        "start": start,
    }
    if "offsets" in meta:
        item["offsets"] = np.asarray(meta["offsets"], dtype=np.float32)  # (J, 3)
    return item


def mirror_item(item: dict, representation) -> dict:
    """A training item seen in a mirror: its features and offsets mirrored exactly
    (``Representation.mirror``), left and right swapped in its caption and in its string labels
    ("walk-left" -> "walk-right"), so the pair stays exactly labelled."""
    motion, offsets = representation.mirror(item["motion"], item.get("offsets"))
    labels = {k: mirror_caption(v) if isinstance(v, str) else v for k, v in item["labels"].items()}
    out = item | {"motion": motion, "text": mirror_caption(item["text"]), "labels": labels}
    if offsets is not None:
        out["offsets"] = offsets.astype(np.float32)
    return out


def pick_text(texts: list[str], rng: np.random.Generator) -> str:
    return texts[int(rng.integers(len(texts)))] if texts else ""


class Collate:
    """Pads windows to the longest in the batch and normalises with the shard set's stats.

    Returns ``motion`` (B, T, D) normalised and zero at padding, ``mask`` (B, T) True on real
    frames, ``lengths`` (B,), ``text`` (list of B captions, "" when unlabeled), ``id``,
    ``category``, ``labels`` (each clip's label dict, {} when it has none), ``offsets``
    (B, J, 3) when every clip carries them, and ``shard_set`` (B,) for samples of a mixture.
    """

    def __init__(self, mean: np.ndarray | None = None, std: np.ndarray | None = None):
        self.mean = None if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        self.std = None if std is None else torch.as_tensor(std, dtype=torch.float32)

    def __call__(self, items: list[dict]) -> dict:
        lengths = torch.tensor([len(it["motion"]) for it in items])
        B, T, D = len(items), int(lengths.max()), items[0]["motion"].shape[1]
        motion = torch.zeros(B, T, D)
        for b, it in enumerate(items):
            x = torch.from_numpy(np.ascontiguousarray(it["motion"]))
            if self.mean is not None:
                x = (x - self.mean) / self.std
            motion[b, : len(x)] = x
        batch = {
            "motion": motion,
            "mask": length_mask(lengths, T),
            "lengths": lengths,
            "text": [it["text"] for it in items],
            "id": [it["id"] for it in items],
            "category": [it["category"] for it in items],
            "labels": [it["labels"] for it in items],
        }
        if all("offsets" in it for it in items):
            batch["offsets"] = torch.from_numpy(np.stack([it["offsets"] for it in items]))
        if all("shard_set" in it for it in items):  # a mixture's samples: the index of each one's set
            batch["shard_set"] = torch.tensor([it["shard_set"] for it in items])
        return batch
