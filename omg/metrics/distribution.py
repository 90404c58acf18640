"""Distances between the real and the generated feature distributions: FID and its variants, 1-NNA.

Features come from a text–motion evaluator, (N, F) per batch. FID keeps running sums of x and
x xᵀ in float64 (memory independent of N, and a cheap DDP ``sum``); 1-NNA needs every sample and
keeps them as ``cat`` states.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from omg.errors import UsageError
from omg.metrics.base import EvalBatch, GenerationMetric
from omg.registry import METRICS


def _psd_sqrt(a: Tensor) -> Tensor:
    """Square root of a symmetric positive semi-definite matrix; round-off negatives become 0."""
    eigvals, eigvecs = torch.linalg.eigh(a)
    return (eigvecs * eigvals.clamp_min(0).sqrt()) @ eigvecs.mT


def frechet_distance(mu1: Tensor, sigma1: Tensor, mu2: Tensor, sigma2: Tensor) -> Tensor:
    """‖μ1 − μ2‖² + tr(Σ1) + tr(Σ2) − 2 tr((Σ1 Σ2)^½), computed in float64.

    Σ1 Σ2 has the eigenvalues of the symmetric PSD matrix A Σ2 A with A = Σ1^½, so the trace of
    its square root is Σ √λ over a symmetric eigendecomposition. Unlike ``sqrtm`` of the
    non-symmetric product this stays exact when a covariance is (near-)singular, e.g. fewer
    samples than features.
    """
    mu1, sigma1, mu2, sigma2 = (t.double() for t in (mu1, sigma1, mu2, sigma2))
    a = _psd_sqrt(sigma1)
    product = a @ sigma2 @ a
    eigvals = torch.linalg.eigvalsh((product + product.mT) / 2)
    trace_sqrt = eigvals.clamp_min(0).sqrt().sum()
    distance = (mu1 - mu2).square().sum() + sigma1.trace() + sigma2.trace() - 2 * trace_sqrt
    return distance.clamp_min(0)  # round-off can take a zero distance just below 0


class _GaussianStats(Metric):
    """Per-group running float64 sums of x and x xᵀ for the real and the generated set."""

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, num_features: int, num_groups: int = 1, **kwargs):
        super().__init__(**kwargs)
        if num_features < 1 or num_groups < 1:
            raise UsageError(f"num_features and num_groups must be >= 1, got {num_features} and {num_groups}")
        self.num_features = num_features
        G, F = num_groups, num_features
        for split in ("real", "gen"):
            self.add_state(f"{split}_sum", torch.zeros(G, F, dtype=torch.float64), dist_reduce_fx="sum")
            self.add_state(f"{split}_outer", torch.zeros(G, F, F, dtype=torch.float64), dist_reduce_fx="sum")
            self.add_state(f"{split}_count", torch.zeros(G, dtype=torch.long), dist_reduce_fx="sum")

    def _accumulate(self, features: Tensor, groups: Tensor, real: bool) -> None:
        if features.ndim != 2 or features.shape[1] != self.num_features:
            raise ValueError(f"expected features of shape (N, {self.num_features}), got {tuple(features.shape)}")
        x = features.detach().double()
        split = "real" if real else "gen"
        total, outer, count = (getattr(self, f"{split}_{s}") for s in ("sum", "outer", "count"))
        total.index_add_(0, groups, x)
        count.index_add_(0, groups, torch.ones_like(groups))
        for g in groups.unique():  # one (F, F) product per group, not N of them
            xg = x[groups == g]
            outer[g] += xg.mT @ xg

    def _frechet(self, g: int) -> Tensor:
        """FID of group ``g``; NaN where either set has fewer than two samples."""
        stats = []
        for split in ("real", "gen"):
            n = getattr(self, f"{split}_count")[g]
            if n < 2:
                return torch.tensor(float("nan"), dtype=torch.float64, device=self.device)
            mu = getattr(self, f"{split}_sum")[g] / n
            cov = (getattr(self, f"{split}_outer")[g] - n * torch.outer(mu, mu)) / (n - 1)
            stats += [mu, cov]
        return frechet_distance(*stats)


@METRICS.register("fid")
class FID(GenerationMetric, _GaussianStats):
    """Fréchet distance between Gaussians fitted to real and generated evaluator features."""

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.real, real=True)
        self.update(batch.gen, real=False)

    def update(self, features: Tensor, real: bool) -> None:
        """features: (N, F) evaluator embeddings of real (``real=True``) or generated motions."""
        self._accumulate(features, torch.zeros(len(features), dtype=torch.long, device=features.device), real)

    def compute(self) -> Tensor:
        fid = self._frechet(0)
        if fid.isnan():
            raise ValueError(
                f"FID needs at least 2 real and 2 generated samples, got {int(self.real_count[0])} "
                f"and {int(self.gen_count[0])}"
            )
        return fid


@METRICS.register("fid_ood")
class FIDOOD(FID):
    """FID of motions generated from out-of-distribution prompts against the whole real set.

    Same maths as FID; a separate name so that both can be logged side by side. Its real set is
    not the prompts' own motions, so a prompt-set pass cannot feed it.
    """

    from_prompts = False


@METRICS.register("intra_fid")
class IntraFID(GenerationMetric, _GaussianStats):
    """FID within each category label, averaged over the categories present in both sets.

    ``compute()`` returns ``{"intra_fid": mean, "intra_fid/<category>": fid, ...}``; a category with
    fewer than two real or generated samples reports NaN and is left out of the mean.
    """

    def __init__(self, num_features: int, categories: Sequence[str], **kwargs):
        if len(set(categories)) != len(categories):
            raise UsageError(f"category names must be unique, got {list(categories)}")
        super().__init__(num_features, num_groups=len(categories), **kwargs)
        self.categories = list(categories)

    def update(self, features: Tensor, labels: Tensor, real: bool) -> None:
        """features: (N, F); labels: (N,) indices into ``categories``."""
        labels = labels.long()
        if labels.numel() and not 0 <= int(labels.min()) <= int(labels.max()) < len(self.categories):
            raise ValueError(f"labels must lie in 0..{len(self.categories) - 1}, got {labels.unique().tolist()}")
        self._accumulate(features, labels, real)

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.real, batch.categories(True), real=True)
        self.update(batch.gen, batch.categories(False), real=False)

    def compute(self) -> dict[str, Tensor]:
        per_category = torch.stack([self._frechet(g) for g in range(len(self.categories))])
        if per_category.isnan().all():
            raise ValueError("IntraFID: no category has at least 2 real and 2 generated samples")
        out = {"intra_fid": per_category.nanmean()}
        out.update({f"intra_fid/{name}": fid for name, fid in zip(self.categories, per_category)})
        return out


@METRICS.register("one_nna")
class OneNNA(GenerationMetric, Metric):
    """1-nearest-neighbour accuracy two-sample test over real ∪ generated features.

    Each sample is classified by the set of its nearest other sample (leave-one-out, Euclidean).
    0.5 means the sets are indistinguishable, 1.0 fully separated. Exact ties go to the lower
    index, i.e. to the real set.
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, chunk_size: int = 1024, **kwargs):
        super().__init__(**kwargs)
        self.chunk_size = chunk_size  # rows of the distance matrix held at once
        self.add_state("real", default=[], dist_reduce_fx="cat")
        self.add_state("gen", default=[], dist_reduce_fx="cat")

    def update(self, features: Tensor, real: bool) -> None:
        """features: (N, F) evaluator embeddings of real (``real=True``) or generated motions."""
        (self.real if real else self.gen).append(features.detach().double())

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.real, real=True)
        self.update(batch.gen, real=False)

    def compute(self) -> Tensor:
        real, gen = dim_zero_cat(self.real), dim_zero_cat(self.gen)
        if not len(real) or not len(gen):
            raise ValueError(f"OneNNA needs real and generated samples, got {len(real)} and {len(gen)}")
        x = torch.cat([real, gen])
        is_real = torch.arange(len(x), device=x.device) < len(real)
        correct = torch.zeros((), dtype=torch.float64, device=x.device)
        for start in range(0, len(x), self.chunk_size):
            rows = torch.arange(start, min(start + self.chunk_size, len(x)), device=x.device)
            dist = torch.cdist(x[rows], x)
            dist[torch.arange(len(rows), device=x.device), rows] = float("inf")  # leave one out
            correct += (is_real[dist.argmin(dim=1)] == is_real[rows]).sum()
        return correct / len(x)
