"""The cross-category downstream task of habit transfer ("Behave Your Motion", Sec. 4): every
validation motion is transferred to every other category with at least ``min_samples`` real
samples, and the FID of the transferred motions against that category's real motion is averaged
over the categories."""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from omg.metrics.distribution import IntraFID
from omg.registry import METRICS


@METRICS.register("cross_category_fid")
class CrossCategoryFID(IntraFID):
    """FID per target category between motions transferred into it and its real motions, averaged.

    ``update(features, category, real)``: real motions under their own category, transferred motions
    under their target category. Categories with fewer than ``min_samples`` real samples (the paper:
    5) are left out. ``compute()`` returns ``{"cross_category_fid": mean, "cross_category_fid/<category>": fid}``.
    """

    from_prompts = False  # transferred motions, not generations from a prompt set

    def __init__(self, num_features: int, categories: Sequence[str], min_samples: int = 5, **kwargs):
        super().__init__(num_features, categories, **kwargs)
        self.min_samples = min_samples

    def compute(self) -> dict[str, Tensor]:
        per_category = torch.stack([
            self._frechet(g) if int(self.real_count[g]) >= self.min_samples else
            torch.tensor(float("nan"), dtype=torch.float64, device=self.device)
            for g in range(len(self.categories))
        ])
        if per_category.isnan().all():
            raise ValueError(f"CrossCategoryFID: no category has {self.min_samples} real and 2 transferred samples")
        out = {"cross_category_fid": per_category.nanmean()}
        out.update({f"cross_category_fid/{name}": fid for name, fid in zip(self.categories, per_category)})
        return out
