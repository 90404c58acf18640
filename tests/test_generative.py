"""The one generation interface: the commands ask a model's card, never its class, and a request the
card cannot answer is one line before anything is sampled."""

from __future__ import annotations

import ast

import pytest

from helpers import REPO
from omg.errors import UsageError
from omg.generation.protocol import GenerationCard, GenerationRequest, check_request

FAMILY_CLASSES = {"PretrainModule", "ControlNetModule", "MotionDiffusionModule", "OmniMotionModule", "HabitVQModule",
                  "HabitPriorModule"}


def test_the_commands_that_generate_never_check_a_family_class():
    for name in ("generate.py", "habit.py"):
        tree = ast.parse((REPO / "omg/tools" / name).read_text())
        checked = {node.args[1].id for node in ast.walk(tree) if isinstance(node, ast.Call)
                   and getattr(node.func, "id", None) in ("isinstance", "issubclass")
                   and isinstance(node.args[1], ast.Name)}
        assert not checked & FAMILY_CLASSES, (name, checked)


TEXT = GenerationCard(family="omg", skeleton="smpl22", representation="humanml3d263", fps=20.0, inputs=("text",),
                      max_frames=1200, samplers=("ddim", "dpmpp"), max_steps=1000, default_steps=200)
PRIOR = GenerationCard(family="omg", skeleton="smpl22", representation="humanml3d263", fps=20.0,
                       inputs=("unconditional",), max_frames=1200, samplers=("ddim",), max_steps=1000)
ANIMAL = GenerationCard(family="omgpt", skeleton="smal35", representation="maa", fps=20.0,
                        inputs=("text", "motion", "species"), needs=("text",), species=("cat", "dog"),
                        source_generator=True)
HABIT = GenerationCard(family="habit", skeleton="smal35", representation="quatvel", fps=30.0,
                       inputs=("motion", "species"), needs=("motion", "species"), species=("dog", "horse"),
                       open_species=True)


@pytest.mark.parametrize("card, request_fields, says", [
    (TEXT, {"prompts": None}, "M generates from prompts: give them"),
    (TEXT, {"species": "dog"}, "M does not generate from a species (--animal); it takes prompts"),
    (TEXT, {"source": object()}, "M does not generate from a source motion (--from_motion); it takes prompts"),
    (TEXT, {"frames": 1}, "--length must give 2..1200 frames at 20 fps, got 1"),
    (TEXT, {"steps": 1001}, "--steps must be in 1..1000 (the checkpoint's diffusion steps), got 1001"),
    (PRIOR, {}, "M is an unconditional pretraining checkpoint: it samples without a condition"),
    (ANIMAL, {"species": "horse"}, "unknown animal 'horse'; this checkpoint knows: cat, dog"),
    (ANIMAL, {"prompts": None, "source": object()}, "M needs prompts"),
    (HABIT, {"prompts": None, "source": object()}, "M needs a species (--animal)"),
    (HABIT, {"prompts": None, "species": "camel"}, "M generates from a source motion (--from_motion) and a species"),
    (HABIT, {"species": "camel", "source": object()}, "M does not generate from prompts"),
    (HABIT, {"prompts": None, "species": "camel", "source": object(), "sampler": "ddim"},
     "--sampler: M has no sampler to choose"),
])
def test_a_request_the_card_cannot_answer_is_one_line(card, request_fields, says):
    request = GenerationRequest(**{"prompts": ["a person walks"], "frames": 40, **request_fields})
    with pytest.raises(UsageError) as error:
        check_request(card, request, "M")
    assert str(error.value).startswith(says) and "\n" not in str(error.value), str(error.value)


def test_requests_the_cards_answer_pass():
    check_request(TEXT, GenerationRequest(prompts=["a person walks"], frames=40, steps=20, sampler="dpmpp"), "M")
    check_request(PRIOR, GenerationRequest(prompts=None, frames=40), "M")
    check_request(ANIMAL, GenerationRequest(prompts=["a dog jumps"], frames=40, species="cat"), "M")
    check_request(HABIT, GenerationRequest(prompts=None, frames=40, species="a camel", source=object()), "M")
