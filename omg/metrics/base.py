"""What every metric shares: the batch an evaluation pass feeds it, the one interface it is fed
through, and a DDP-safe running mean."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor
from torchmetrics import Metric


@dataclass
class EvalBatch:
    """What one evaluation batch offers a metric: evaluator embeddings (N, E) of the texts and
    of the real and generated motions, category indices (N,), decoded joints (N, T, J, 3) with
    the frame mask (N, T), each row's clip labels, and MultiModality's repeated generations
    (M, E) with their prompt ids (M,). Fields a pass does not need are None.

    ``gen_category`` (N',): the categories of the generated rows where they are not the real rows'
    (habit transfer: real motion of a category against motion transferred into it from others,
    the two sets of different sizes); None: ``category`` labels both."""

    text: Tensor | None = None
    real: Tensor | None = None
    gen: Tensor | None = None
    category: Tensor | None = None
    mask: Tensor | None = None
    real_joints: Tensor | None = None
    gen_joints: Tensor | None = None
    mm: Tensor | None = None
    mm_ids: Tensor | None = None
    labels: list[dict] | None = None
    gen_category: Tensor | None = None

    def motion(self, real: bool) -> Tensor | None:
        return self.real if real else self.gen

    def categories(self, real: bool) -> Tensor | None:
        return self.category if real or self.gen_category is None else self.gen_category

    def joints(self, real: bool) -> Tensor | None:
        return self.real_joints if real else self.gen_joints


class GenerationMetric:
    """The interface the evaluation (``omg.evaluation.evaluate``) feeds every metric through,
    built-in or plugin: ``eval_update(batch, real)``, where ``real`` asks a metric that
    describes one set of motions to take the real motions in place of the generated ones (the
    reference row of the published tables). The class flags say what the pass must provide:

    - ``reference``: the metric describes one set of motions; it is also reported for the real
      motions, as ``real/<name>``;
    - ``repeated``: it is fed the repeated generations of the first prompts (MultiModality)
      instead of the prompt batches;
    - ``needs_joints``: it reads decoded joint positions;
    - ``from_prompts``: False for a metric that needs inputs a prompt set cannot give;
    - ``needs_real``: it compares with the real motions of the prompts (False: it can score a
      prompt file, whose prompts have none);
    - ``needs_embeddings``: it reads the evaluator's embeddings (False: it needs no evaluator).
    """

    reference: ClassVar[bool] = False
    repeated: ClassVar[bool] = False
    needs_joints: ClassVar[bool] = False
    from_prompts: ClassVar[bool] = True
    needs_real: ClassVar[bool] = True
    needs_embeddings: ClassVar[bool] = True

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        raise NotImplementedError(f"{type(self).__name__} does not say how an evaluation batch feeds it")


class RunningMean(Metric):
    """A running mean in float64 whose sum and count DDP reduces by summing."""

    is_differentiable = False
    full_state_update = False

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.add_state("total", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", torch.tensor(0), dist_reduce_fx="sum")

    def accumulate(self, total: Tensor, count: Tensor | int) -> None:
        self.total += total
        self.count += count

    def compute(self) -> Tensor:
        return self.total / self.count
