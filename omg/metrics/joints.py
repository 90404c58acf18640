"""Metrics on joint positions (B, T, J, 3) in metres, +Y up, floor at y = 0, with a (B, T) frame mask."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics import Metric

from omg.errors import UsageError
from omg.metrics.base import EvalBatch, GenerationMetric, RunningMean
from omg.registry import METRICS
from omg.skeleton import Skeleton, get_skeleton


def _frame_mask(joints: Tensor, mask: Tensor | None) -> Tensor:
    if joints.ndim != 4 or joints.shape[-1] != 3:
        raise ValueError(f"expected joint positions of shape (B, T, J, 3), got {tuple(joints.shape)}")
    if mask is None:
        return torch.ones(joints.shape[:2], dtype=torch.bool, device=joints.device)
    if mask.shape != joints.shape[:2]:
        raise ValueError(f"expected a frame mask of shape {tuple(joints.shape[:2])}, got {tuple(mask.shape)}")
    return mask.bool()


@METRICS.register("mpjpe")
class MPJPE(GenerationMetric, RunningMean):
    """Mean per-joint position error: Euclidean distance averaged over joints and valid frames. Fed by an
    evaluation, it compares each generated motion with the real motion of its row (habit transfer: the
    transferred motion with its source)."""

    higher_is_better = False
    needs_joints = True
    from_prompts = False  # a generation from a prompt is not meant to match one real clip joint by joint

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.gen_joints, batch.real_joints, batch.mask)

    def update(self, pred: Tensor, target: Tensor, mask: Tensor | None = None) -> None:
        """pred, target: (B, T, J, 3); mask: (B, T), True on real (unpadded) frames."""
        if pred.shape != target.shape:
            raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
        mask = _frame_mask(pred, mask)
        error = (pred.detach().double() - target.detach().double()).norm(dim=-1)  # (B, T, J)
        self.accumulate((error * mask[..., None]).sum(), mask.sum() * pred.shape[2])


@METRICS.register("foot_skating")
class FootSkating(GenerationMetric, Metric):
    """Foot-skating ratio, the GMD definition (Karunratanakul et al. 2023, also used for MDM/OmniControl).

    Per frame transition t → t+1 and foot joint: the foot is in contact when its height is below
    ``height_threshold`` (5 cm) in both frames, and skates when in contact while its horizontal
    (XZ) speed exceeds ``speed_threshold`` (0.5 m/s) both at t and averaged over a centred window
    of ``window`` (5) transitions (zeros beyond the clip, as scipy's ``uniform_filter1d`` with
    ``mode="constant"``). A transition skates when any foot joint does. The ratio is skating
    transitions over valid transitions per clip, averaged over clips.

    Foot joints default to the skeleton's ``feet_left + feet_right``. GMD tests the SMPL toes
    only (``joints=(10, 11)``); the ankles (7, 8) sit about 6 cm up in the rest pose, so adding
    them rarely changes the count.
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(
        self,
        skeleton: str | Skeleton = "smpl22",
        fps: float = 20.0,
        height_threshold: float = 0.05,
        speed_threshold: float = 0.5,
        window: int = 5,
        joints: Sequence[int] | None = None,
        **kwargs,
    ):
        super().__init__(**kwargs)
        skeleton = get_skeleton(skeleton)
        self.feet = list(joints if joints is not None else skeleton.feet)
        if not self.feet:
            raise UsageError(f"skeleton {skeleton.name!r} names no feet; pass the foot joints as joints=[...]")
        if fps <= 0 or window < 1:
            raise UsageError(f"need fps > 0 and window >= 1, got fps={fps}, window={window}")
        self.fps, self.window = fps, window
        self.height_threshold, self.speed_threshold = height_threshold, speed_threshold
        self.add_state("total", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", torch.tensor(0), dist_reduce_fx="sum")

    def update(self, joints: Tensor, mask: Tensor | None = None) -> None:
        """joints: (B, T, J, 3) positions; mask: (B, T), True on real (unpadded) frames."""
        mask = _frame_mask(joints, mask)
        if joints.shape[1] < 2:  # no frame transitions to judge
            return
        feet = joints[:, :, self.feet].detach().double()  # (B, T, K, 3)
        valid = mask[:, 1:] & mask[:, :-1]  # (B, T-1) transitions between two real frames
        speed = (feet[:, 1:, :, [0, 2]] - feet[:, :-1, :, [0, 2]]).norm(dim=-1) * self.fps  # (B, T-1, K)
        speed = speed * valid[..., None]
        B, L, K = speed.shape
        avg = F.avg_pool1d(  # count_include_pad: zeros beyond the clip count, as in GMD
            speed.permute(0, 2, 1).reshape(B * K, 1, L), self.window, stride=1, padding=self.window // 2
        )[..., :L].reshape(B, K, L).permute(0, 2, 1)
        height = feet[..., 1]  # (B, T, K)
        contact = (height[:, :-1] < self.height_threshold) & (height[:, 1:] < self.height_threshold)
        skating = (contact & (speed > self.speed_threshold) & (avg > self.speed_threshold)).any(-1) & valid
        transitions = valid.sum(1)  # (B,)
        clips = transitions > 0
        self.total += (skating.sum(1)[clips].double() / transitions[clips]).sum()
        self.count += clips.sum()

    reference = True
    needs_joints = True
    needs_real = False
    needs_embeddings = False

    def eval_update(self, batch: EvalBatch, real: bool = False) -> None:
        self.update(batch.joints(real), batch.mask)

    def compute(self) -> Tensor:
        return self.total / self.count
