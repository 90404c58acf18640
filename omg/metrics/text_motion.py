"""Agreement between matched text and motion features: R-precision, MM-Dist, CLIP score.

Inputs are evaluator embeddings of the texts and of the motions generated from them, (N, F)
each, row i of one matching row i of the other.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from omg.errors import UsageError
from omg.metrics.base import EvalBatch, GenerationMetric, RunningMean
from omg.registry import METRICS


def _check_pairs(text: Tensor, motion: Tensor) -> None:
    if text.ndim != 2 or text.shape != motion.shape:
        raise ValueError(
            f"expected text and motion features of the same shape (N, F), got {tuple(text.shape)} "
            f"and {tuple(motion.shape)}"
        )


class TextMotionPairs(GenerationMetric):
    """Fed each text with the motion made from it (or, for the reference row, its real motion)."""

    reference = True

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.text, batch.motion(real))


@METRICS.register("r_precision")
class RPrecision(TextMotionPairs, Metric):
    """Text→motion retrieval top-k accuracy in pools of 32 (the HumanML3D protocol).

    The samples are shuffled with a seeded permutation and cut into pools of ``pool_size``
    (the incomplete last pool is dropped, as HumanML3D's ``drop_last`` loader does). Within a pool
    each text ranks its own motion among the pool's motions by Euclidean distance; a hit at k
    means fewer than k mismatched motions lie strictly closer than the matched one.
    ``compute()`` returns ``{"r_precision/top1": ..., "r_precision/top2": ..., ...}``.

    Under DDP the gathered samples are in rank order, so pools match a single process whenever
    each rank holds a contiguous part of the data; otherwise they differ only in which samples
    share a pool, as between two shuffles.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, pool_size: int = 32, top_k: int = 3, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        if not 1 <= top_k <= pool_size:
            raise UsageError(f"need 1 <= top_k <= pool_size, got top_k={top_k}, pool_size={pool_size}")
        self.pool_size, self.top_k, self.seed = pool_size, top_k, seed
        self.add_state("text", default=[], dist_reduce_fx="cat")
        self.add_state("motion", default=[], dist_reduce_fx="cat")

    def update(self, text_features: Tensor, motion_features: Tensor) -> None:
        _check_pairs(text_features, motion_features)
        self.text.append(text_features.detach().double())
        self.motion.append(motion_features.detach().double())

    def compute(self) -> dict[str, Tensor]:
        text, motion = dim_zero_cat(self.text), dim_zero_cat(self.motion)
        pools = len(text) // self.pool_size
        if pools == 0:
            raise ValueError(f"RPrecision needs at least pool_size={self.pool_size} samples, got {len(text)}")
        order = torch.randperm(len(text), generator=torch.Generator().manual_seed(self.seed))
        order = order[: pools * self.pool_size].to(text.device)
        text = text[order].view(pools, self.pool_size, -1)
        motion = motion[order].view(pools, self.pool_size, -1)
        dist = torch.cdist(text, motion)  # (pools, P, P): text i against every motion in its pool
        matched = dist.diagonal(dim1=1, dim2=2)  # (pools, P)
        rank = (dist < matched[..., None]).sum(-1)  # mismatched motions strictly closer
        return {f"r_precision/top{k}": (rank < k).double().mean() for k in range(1, self.top_k + 1)}


@METRICS.register("mm_dist")
class MMDist(TextMotionPairs, RunningMean):
    """Multimodal distance: mean Euclidean distance between matched text and motion features."""

    higher_is_better = False

    def update(self, text_features: Tensor, motion_features: Tensor) -> None:
        _check_pairs(text_features, motion_features)
        text, motion = text_features.detach().double(), motion_features.detach().double()
        self.accumulate((text - motion).norm(dim=1).sum(), len(text_features))


@METRICS.register("clip_score")
class CLIPScore(TextMotionPairs, RunningMean):
    """Mean cosine similarity between text and motion features in the text-aligned space.

    Plain cosine in [-1, 1]: no ×100 scaling and no clamping at 0.
    """

    higher_is_better = True

    def update(self, text_features: Tensor, motion_features: Tensor) -> None:
        _check_pairs(text_features, motion_features)
        text, motion = text_features.detach().double(), motion_features.detach().double()
        self.accumulate(F.cosine_similarity(text, motion, dim=1).sum(), len(text_features))


@METRICS.register("label_accuracy")
class LabelAccuracy(GenerationMetric, Metric):
    """How often the evaluator recognises a motion's class: each motion's nearest caption (among
    the distinct captions of the pass, Euclidean in the evaluator's space) carries the same value
    of the clip label ``label`` (e.g. a take's ``content``: walk, bow, ...) as the motion's own.

    ``compute()`` returns ``{"label_accuracy": overall, "label_accuracy/<value>": per class}``;
    chance is about 1 / number of classes. ``values`` (every value of the label in the prompt
    set, filled in by the evaluation) makes the class indices the same on every rank. Motions
    whose clip has no such label are left out.
    """

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

    def __init__(self, label: str = "content", labels: dict[str, list[str]] | None = None, **kwargs):
        super().__init__(**kwargs)
        self.label = label
        self.values = list((labels or {}).get(label, []))
        if not self.values:
            raise UsageError(f"label_accuracy: no clip of the evaluation set has a {label!r} label "
                             "(set label: to one of the clips' labels)")
        self.add_state("text", default=[], dist_reduce_fx="cat")
        self.add_state("motion", default=[], dist_reduce_fx="cat")
        self.add_state("klass", default=[], dist_reduce_fx="cat")

    def update(self, text_features: Tensor, motion_features: Tensor, labels: list[dict]) -> None:
        """Matched text and motion features (N, F) and each row's clip labels."""
        _check_pairs(text_features, motion_features)
        index = {v: i for i, v in enumerate(self.values)}
        rows = [i for i, lab in enumerate(labels) if str(lab.get(self.label)) in index]
        if rows:
            keep = torch.tensor(rows, device=text_features.device)
            self.text.append(text_features[keep].detach().double())
            self.motion.append(motion_features[keep].detach().double())
            self.klass.append(torch.tensor([index[str(labels[i][self.label])] for i in rows], device=keep.device))

    reference = True

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.text, batch.motion(real), batch.labels or [])

    def compute(self) -> dict[str, Tensor]:
        text, motion, klass = dim_zero_cat(self.text), dim_zero_cat(self.motion), dim_zero_cat(self.klass)
        captions, inverse = torch.unique(text, dim=0, return_inverse=True)  # distinct captions
        caption_class = torch.zeros(len(captions), dtype=klass.dtype, device=klass.device)
        caption_class[inverse] = klass
        predicted = caption_class[torch.cdist(motion, captions).argmin(dim=1)]
        hit = (predicted == klass).double()
        out = {"label_accuracy": hit.mean()}
        for i, value in enumerate(self.values):
            if (klass == i).any():
                out[f"label_accuracy/{value}"] = hit[klass == i].mean()
        return out
