"""LightningModules, one per task."""

from omg.lit.controlnet import ControlNetModule
from omg.lit.pretrain import PretrainModule

__all__ = ["ControlNetModule", "PretrainModule"]
