"""LightningModules, one per task."""

from omg.lit.pretrain import PretrainModule

__all__ = ["PretrainModule"]
