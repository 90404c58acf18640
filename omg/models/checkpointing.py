"""Activation checkpointing, applied to a model's blocks from outside its code: the LightningModules call it
(``activation_checkpointing``), and ``omg bench plan``'s estimate is checked against a step that does."""

from __future__ import annotations

from collections.abc import Iterable

from torch import nn
from torch.distributed._composable import checkpoint as checkpoint_activations


def checkpoint_each(modules: Iterable[nn.Module]) -> None:
    """Recompute each module's activations in backward instead of keeping them (torch's
    composable ``checkpoint``: parameter names and checkpoints stay as they are)."""
    for module in modules:
        checkpoint_activations(module)
