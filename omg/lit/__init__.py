"""LightningModules, one per task."""

from omg.lit.controlnet import ControlNetModule
from omg.lit.evaluator import EvaluatorModule
from omg.lit.pretrain import PretrainModule

__all__ = ["ControlNetModule", "EvaluatorModule", "PretrainModule"]
