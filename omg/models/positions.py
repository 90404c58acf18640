"""Fixed sinusoidal position codes, shared by the transformers that read motion frames in order
(the evaluator, OmniMotionGPT's autoencoders, the habit encoder); MotionDiT uses rotary embeddings."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def sinusoidal_positions(length: int, dim: int, device: torch.device | None = None) -> Tensor:
    """(length, dim) sin/cos features of positions 0 .. length - 1 (Vaswani et al.): any clip length works."""
    pos = torch.arange(length, device=device, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, device=device, dtype=torch.float32) * (-math.log(10000.0) / dim))
    out = torch.zeros(length, dim, device=device)
    out[:, 0::2] = torch.sin(pos * freq)
    out[:, 1::2] = torch.cos(pos * freq[: dim // 2])
    return out
