"""An fp32 exponential moving average of a module's trainable weights.

Kept outside the module on purpose: mixed-precision strategies (DeepSpeed bf16) cast the
module's parameters and buffers, and an EMA rounded to bf16 every step stops moving. The
state travels in checkpoints under ``checkpoint["ema"]``, which DeepSpeed stores with its
client state, so it survives ZeRO checkpoints too.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch
from torch import nn


class EMA:
    def __init__(self, module: nn.Module, decay: float = 0.9999, warmup: bool = True):
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.decay, self.warmup, self.updates = decay, warmup, 0
        self.shadow = {n: p.detach().float().clone() for n, p in module.named_parameters() if p.requires_grad}

    def current_decay(self) -> float:
        # short runs average over their own length instead of the initial weights
        return min(self.decay, (1 + self.updates) / (10 + self.updates)) if self.warmup else self.decay

    @torch.no_grad()
    def update(self, module: nn.Module) -> None:
        d = self.current_decay()
        for name, p in module.named_parameters():
            if name in self.shadow:
                shadow = self.shadow[name]
                if shadow.device != p.device:
                    self.shadow[name] = shadow = shadow.to(p.device)
                shadow.lerp_(p.detach().float(), 1.0 - d)
        self.updates += 1

    @torch.no_grad()
    def copy_to(self, module: nn.Module) -> None:
        for name, p in module.named_parameters():
            if name in self.shadow:
                p.copy_(self.shadow[name].to(p.dtype))

    @contextmanager
    def swapped_in(self, module: nn.Module):
        """Run with the EMA weights, then restore the trained ones."""
        backup = {n: p.detach().clone() for n, p in module.named_parameters() if n in self.shadow}
        self.copy_to(module)
        try:
            yield module
        finally:
            with torch.no_grad():
                for name, p in module.named_parameters():
                    if name in backup:
                        p.copy_(backup[name])

    def state_dict(self) -> dict:
        return {"decay": self.decay, "updates": self.updates, "shadow": {n: t.cpu() for n, t in self.shadow.items()}}

    def load_state_dict(self, state: dict) -> None:
        missing = set(self.shadow) - set(state["shadow"])
        if missing:
            raise KeyError(f"EMA state lacks {len(missing)} parameters, e.g. {sorted(missing)[:3]}")
        self.decay, self.updates = state["decay"], state["updates"]
        device = next(iter(self.shadow.values())).device
        self.shadow = {n: state["shadow"][n].float().to(device) for n in self.shadow}
