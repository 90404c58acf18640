"""Evaluation metrics as torchmetrics ``Metric`` classes, registered in ``omg.registry.METRICS`` and fed by
the evaluation through one interface (``omg.metrics.base.GenerationMetric.eval_update``).

Every state is declared with a DDP reduction (``sum`` for running sums, ``cat`` for feature
lists), so ``compute()`` gives the same result on every rank as one process seeing all data.
"""

from omg.metrics.base import EvalBatch, GenerationMetric
from omg.metrics.distribution import FID, FIDOOD, IntraFID, OneNNA, frechet_distance
from omg.metrics.diversity import Diversity, MultiModality
from omg.metrics.following import PromptFollowing
from omg.metrics.habit import CrossCategoryFID
from omg.metrics.joints import MPJPE, FootSkating
from omg.metrics.text_motion import CLIPScore, LabelAccuracy, MMDist, RPrecision

__all__ = [
    "CLIPScore",
    "CrossCategoryFID",
    "Diversity",
    "EvalBatch",
    "FID",
    "FIDOOD",
    "FootSkating",
    "GenerationMetric",
    "IntraFID",
    "LabelAccuracy",
    "MMDist",
    "MPJPE",
    "MultiModality",
    "OneNNA",
    "PromptFollowing",
    "RPrecision",
    "frechet_distance",
]
