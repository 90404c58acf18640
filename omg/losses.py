"""Training losses: the geometric terms of the diffusion stages, the contrastive InfoNCE of
the text–motion evaluator, and the masked reductions OmniMotionGPT and habit transfer train
with. The λ_t-weighted x̂0 loss belongs to the noise schedule
(``omg.diffusion.Diffusion.loss``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from omg.kinematics import foot_contacts
from omg.motion import Representation


class GeometricLoss:
    """MDM's velocity and foot-contact losses on joint positions decoded from the features
    (shared by OMG's pretraining and ControlNet stages):

        L_vel  = mean over real frame pairs of ‖v̂_t − v_t‖², v the per-frame joint displacement;
        L_foot = mean over real frame pairs of ‖v̂_t,foot‖² where the real foot is in contact.
    """

    def __init__(self, representation: Representation, fps: float):
        self.rep, self.fps = representation, fps

    def __call__(self, x0_hat: Tensor, x0: Tensor, mask: Tensor, offsets: Tensor | None) -> tuple[Tensor, Tensor]:
        """x0_hat, x0: (B, T, D) un-normalised features; mask (B, T). Returns (L_vel, L_foot)."""
        with torch.autocast(x0.device.type, enabled=False):
            pos_hat = self.rep.decode(x0_hat.float(), offsets)  # (B, T, J, 3)
            pos = self.rep.decode(x0.float(), offsets)
            vel_hat = pos_hat[:, 1:] - pos_hat[:, :-1]  # (B, T-1, J, 3)
            vel = pos[:, 1:] - pos[:, :-1]
            pair = (mask[:, 1:] & mask[:, :-1]).float()  # (B, T-1) both frames real
            frames = pair.sum().clamp(min=1)
            l_vel = ((vel_hat - vel).pow(2).mean(dim=(-1, -2)) * pair).sum() / frames

            feet = list(self.rep.skeleton.feet)
            # the representation's own contact labels where it has them (humanml3d263), else
            # HumanML3D's rule on the real positions
            contact = self.rep.foot_contacts(x0.float())  # (B, T, F) or None
            contact = ((contact[:, :-1] > 0.5).float() if contact is not None
                       else foot_contacts(pos, feet, self.fps).float())
            foot_vel = vel_hat[:, :, feet]  # (B, T-1, F, 3)
            l_foot = ((foot_vel.pow(2).sum(-1) * contact).mean(-1) * pair).sum() / frames
        return l_vel, l_foot


def info_nce(logits: Tensor, same: Tensor | None = None) -> Tensor:
    """Symmetric InfoNCE over (B, B) text×motion logits whose diagonal holds the positives.

    ``same`` (B, B) bool marks off-diagonal pairs that are not negatives (a duplicate caption,
    another window of the same clip): they are removed from both softmaxes, so that two equal
    texts are never pushed apart from each other's motion.
    """
    if same is not None:
        off = same & ~torch.eye(len(logits), dtype=torch.bool, device=logits.device)
        logits = logits.masked_fill(off, float("-inf"))
    target = torch.arange(len(logits), device=logits.device)
    return 0.5 * (F.cross_entropy(logits, target) + F.cross_entropy(logits.T, target))


__all__ = ["GeometricLoss", "info_nce"]


def masked_mse(a: Tensor, b: Tensor, mask: Tensor) -> Tensor:
    """Mean squared error over the real entries: a, b (B, L, ...), mask (B, L)."""
    weights = mask.reshape(*mask.shape, *([1] * (a.dim() - mask.dim()))).to(a.dtype)
    per_entry = a[0, 0].numel()
    return ((a - b).square() * weights).sum() / (weights.sum() * per_entry).clamp_min(1)


def cosine_gap(a: Tensor, b: Tensor, rows: Tensor) -> Tensor:
    """Mean of 1 − cos(a, b) over the selected rows (B,) bool."""
    gap = 1 - F.cosine_similarity(a, b, dim=-1)
    return (gap * rows).sum() / rows.sum().clamp_min(1)


def masked_smooth_l1(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean smooth L1 over the real frames: (B, T, F), (B, T, F), (B, T) -> ()."""
    error = F.smooth_l1_loss(pred, target, reduction="none").mean(-1)  # (B, T)
    return (error * mask).sum() / mask.sum().clamp_min(1)
