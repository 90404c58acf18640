"""Spread of generated motions: Diversity over the whole set, MultiModality per text.

Both follow the HumanML3D evaluation: mean Euclidean distance between randomly drawn pairs of
evaluator features, with the draws seeded so that a run is reproducible.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from omg.errors import UsageError
from omg.metrics.base import EvalBatch, GenerationMetric
from omg.registry import METRICS


def _pair_indices(n: int, num_pairs: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """Two independent draws of ``num_pairs`` distinct indices out of ``n`` (HumanML3D's
    ``np.random.choice(n, num_pairs, replace=False)`` twice)."""
    return torch.randperm(n, generator=generator)[:num_pairs], torch.randperm(n, generator=generator)[:num_pairs]


@METRICS.register("diversity")
class Diversity(GenerationMetric, Metric):
    """Mean distance between ``num_pairs`` (300) random pairs of motion features of the whole set."""

    is_differentiable = False
    higher_is_better = None  # closer to the real data's diversity is better
    full_state_update = False

    def __init__(self, num_pairs: int = 300, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.num_pairs, self.seed = num_pairs, seed
        self.add_state("features", default=[], dist_reduce_fx="cat")

    def update(self, features: Tensor) -> None:
        """features: (N, F) evaluator embeddings of motions."""
        self.features.append(features.detach().double())

    reference = True
    needs_real = False  # the spread of the generated motions alone

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.motion(real))

    def compute(self) -> Tensor:
        x = dim_zero_cat(self.features)
        if len(x) < self.num_pairs:
            raise UsageError(
                f"Diversity needs at least num_pairs={self.num_pairs} samples, got {len(x)}; lower num_pairs"
            )
        first, second = _pair_indices(len(x), self.num_pairs, torch.Generator().manual_seed(self.seed))
        return (x[first.to(x.device)] - x[second.to(x.device)]).norm(dim=1).mean()


@METRICS.register("multimodality")
class MultiModality(GenerationMetric, Metric):
    """Mean distance between pairs of motions generated from the same text, averaged over texts.

    Per text (grouped by ``text_ids``, in ascending id order) ``min(num_pairs, n)`` pairs are drawn
    among its n generations as in HumanML3D (10 pairs of 30 repeats there); texts with a single
    generation have no pairs and are skipped.
    """

    is_differentiable = False
    higher_is_better = None  # closer to the real data's multimodality is better
    full_state_update = False

    def __init__(self, num_pairs: int = 10, seed: int = 0, **kwargs):
        super().__init__(**kwargs)
        self.num_pairs, self.seed = num_pairs, seed
        self.add_state("features", default=[], dist_reduce_fx="cat")
        self.add_state("text_ids", default=[], dist_reduce_fx="cat")

    def update(self, features: Tensor, text_ids: Tensor) -> None:
        """features: (N, F) embeddings of generated motions; text_ids: (N,) the text each came from."""
        if text_ids.shape != features.shape[:1]:
            raise ValueError(f"expected text_ids of shape ({len(features)},), got {tuple(text_ids.shape)}")
        self.features.append(features.detach().double())
        self.text_ids.append(text_ids.detach().long())

    repeated = True
    needs_real = False

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        if batch.mm is not None and len(batch.mm):
            self.update(batch.mm, batch.mm_ids)

    def compute(self) -> Tensor:
        x, ids = dim_zero_cat(self.features), dim_zero_cat(self.text_ids)
        generator = torch.Generator().manual_seed(self.seed)
        per_text = []
        for text_id in ids.unique():  # sorted
            group = x[ids == text_id]
            if len(group) < 2:
                continue
            first, second = _pair_indices(len(group), min(self.num_pairs, len(group)), generator)
            per_text.append((group[first.to(x.device)] - group[second.to(x.device)]).norm(dim=1).mean())
        if not per_text:
            raise ValueError("MultiModality needs at least one text with two or more generations")
        return torch.stack(per_text).mean()
