"""LightningModules, one per task."""

from omg.lit.controlnet import ControlNetModule
from omg.lit.evaluator import EvaluatorModule
from omg.lit.habit import HabitPriorModule, HabitVQModule
from omg.lit.omgpt import OmniMotionModule
from omg.lit.pretrain import PretrainModule

__all__ = ["ControlNetModule", "EvaluatorModule", "HabitPriorModule", "HabitVQModule", "OmniMotionModule",
           "PretrainModule"]
