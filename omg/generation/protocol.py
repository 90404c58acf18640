"""The one generation interface of every model family.

A family's generator (``Generator``, found for a trained module by ``omg.generation.registry``)
says in its ``generation_card`` what the model generates from (text, no condition, a source
motion, a species), on which skeleton, at what frame rate and within which frame limits, with
which sampler options and family options; ``generate`` turns a ``GenerationRequest`` into
``GeneratedMotion``s. ``omg generate``, ``omg transfer`` and the server ask a generator only
these, never the module's class, and write what it returns with one writer
(``omg.generation.write``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from omg.errors import UsageError
from omg.generation.progress import ProgressReport

Input = Literal["text", "unconditional", "motion", "species"]
MAX_SECONDS = 60.0  # the longest motion one generation call makes


@dataclass(frozen=True)
class NumberRange:
    """A number a request may set: within [``low``, ``high``] (``low_open``: (low, high]; ``high`` None: no
    upper bound), ``default`` where it is not given (None: none to name, or the model's own)."""

    low: float
    high: float | None = None
    default: float | None = None
    low_open: bool = False

    def read(self, key: str, value: str) -> float:
        """``value`` (text) as a number within the range, else one line naming ``key`` (``number_option``)."""
        return number_option(key, value, self.low, math.inf if self.high is None else self.high, self.low_open)


@dataclass(frozen=True)
class GenerationCard:
    """What a module generates and from what; the page, the API and the CLI read their options here.

    ``inputs``: "text" (prompts), "unconditional" (nothing), "motion" (a source motion file,
    ``read_source``), "species" (a target animal); ``needs``: those every request must give.
    ``samplers``/``max_steps``/``guidance``: a diffusion family's sampling options (the default
    guidance scale), empty for a family without them. ``species``: the animals it knows by name;
    ``open_species``: any other species or description is answered too (by retrieval).
    ``source_generator``: a checkpoint may make the source motion from the prompt (OmniMotionGPT's
    OMG → animal chain). ``timeline``: what ``GenerationRequest.timeline`` may hold (``timeline``: prompt
    segments in time; ``parts``: body parts each with its own text; ``omg.generation.timeline``).
    ``option_ranges``: the bounds and defaults of the ``options`` that are numbers, which ``option`` reads a
    value within; ``ranges`` adds the sampler's steps and guidance."""

    family: str
    skeleton: str
    representation: str
    fps: float
    inputs: tuple[Input, ...]
    needs: tuple[Input, ...] = ()
    min_frames: int = 2
    max_frames: int = 1200
    samplers: tuple[str, ...] = ()
    max_steps: int = 0
    default_steps: int = 0
    guidance: float | None = None
    species: tuple[str, ...] = ()
    open_species: bool = False
    source_generator: bool = False
    source_fixes_length: bool = False  # a source motion sets the output's frames (a transfer)
    deterministic_source: bool = False  # a given source motion yields one motion, whatever num_samples says
    options: dict[str, str] = field(default_factory=dict)  # family options a request may set: name -> meaning
    row_seeds: bool = False  # ``generate`` honours ``GenerationRequest.row_seeds`` (a server may batch requests)
    timeline: tuple[str, ...] = ()  # what a request's timeline may hold: "timeline" (segments), "parts" (body parts)
    # the kinds of spatial constraint ``generate`` takes (``GenerationRequest.control``; omg.generation.control)
    constraints: tuple[str, ...] = ()
    # the feet a constraints file's "contacts" may ask held besides given spans: "model" (the representation's
    # contact channels plant them), "ground" (each estimate puts them on the ground); omg.generation.control
    contacts: tuple[str, ...] = ()
    option_ranges: dict[str, NumberRange] = field(default_factory=dict)  # of ``options``: name -> its range

    def __post_init__(self):
        if unlisted := sorted(set(self.option_ranges) - set(self.options)):
            raise ValueError(f"option_ranges of options the card does not list: {', '.join(unlisted)}")

    def ranges(self) -> dict[str, NumberRange]:
        """Every number a request may set, by its name in a request, with its bounds and default: the sampler's
        ``steps`` (1..``max_steps``) and ``guidance`` where the card has them, and ``option_ranges``."""
        sampling = {}
        if self.samplers:
            sampling["steps"] = NumberRange(1, self.max_steps or None, self.default_steps or None)
        if self.guidance is not None:
            sampling["guidance"] = NumberRange(0.0, None, self.guidance)
        return {**sampling, **self.option_ranges}

    def to_dict(self) -> dict[str, Any]:
        """The card as ``GET /v1/models`` lists it: its fields, ``option_ranges`` within ``ranges``."""
        plain = {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items() if k != "option_ranges"}
        return {**plain, "ranges": {name: asdict(r) for name, r in self.ranges().items()}}


@dataclass
class GenerationRequest:
    """One call's worth of motions: ``num_samples`` per prompt (or in total without prompts).

    ``source``: a motion already read by the module's ``read_source``; ``source_module``: a
    generative module that makes the source motion from each prompt. ``steps``/``sampler``/
    ``guidance`` are None for the family's defaults. ``progress`` hears how far the call is."""

    prompts: list[str] | None
    frames: int
    num_samples: int = 1
    seed: int = 0
    steps: int | None = None
    sampler: str | None = None
    guidance: float | None = None
    species: str | None = None
    source: Any = None
    source_module: Any = None
    batch_size: int = 32
    autocast: Any = None  # a torch dtype
    compile: bool = False
    options: dict[str, Any] = field(default_factory=dict)  # the family's own (``GenerationCard.options``)
    # one noise seed per motion (prompt-major, as ``generate`` returns them) where the card says ``row_seeds``:
    # each motion is then the same whatever it is sampled with (a server batches requests); None: ``seed``
    row_seeds: list[int] | None = None
    # a prompt timeline and body-part composition (``omg.generation.timeline.TimelineFile``), given instead of
    # prompts: each of the ``num_samples`` motions follows it
    timeline: Any = None
    # spatial constraints resolved for one motion of ``frames`` (omg.lit.control.Control), where the card takes them
    control: Any = None
    # who watches the call (``omg.generation.progress``): each batch's start, sampler steps and end; the motions are
    # those of an unwatched call
    progress: ProgressReport | None = None


@dataclass
class GeneratedMotion:
    """One motion as the writer takes it.

    ``features`` (T, D) in the module's representation and ``joints`` (T, J, 3) metres, Y up.
    ``rotations`` = (local quaternions (T, J, 4), root (T, 3), offsets (J, 3)) when the model makes
    rotations: they are written to BVH as they are; else the writer solves them by IK.
    ``companions``: other motions of this one's making, as (file stem, ``{stem}`` standing for the
    motion's, joints (T, J', 3), skeleton name, preview title or None) — OmniMotionGPT's human
    source, a transfer's source.
    ``record``: what ``generation.json`` keeps about it (prompt, repeat, seeds, the animal…)."""

    features: np.ndarray
    joints: np.ndarray
    title: str
    record: dict[str, Any] = field(default_factory=dict)
    rotations: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    companions: list[tuple[str, np.ndarray, str, str | None]] = field(default_factory=list)


@runtime_checkable
class Generator(Protocol):
    """What ``omg generate``, ``omg transfer`` and ``omg serve`` call on a model of any family: its
    trained ``module`` (a LightningModule, which holds training only) seen through its family's adapter."""

    module: Any
    takes_prior: bool  # ``with_prior`` takes a second checkpoint's prior (``--prior_ckpt``)

    def generation_card(self) -> GenerationCard: ...

    def read_source(self, path: Path, joint_map: str | None = None) -> Any: ...

    def generate(self, request: GenerationRequest) -> list[GeneratedMotion]: ...

    def generation_settings(self, request: GenerationRequest) -> dict[str, Any]: ...

    def option(self, key: str, value: str) -> Any: ...

    def with_prior(self, prior: Any) -> None: ...


class ModuleGenerator:
    """What the families' adapters share: the module they generate with, moved with ``to``, and no source
    motion, family option or prior unless the adapter takes one."""

    takes_prior = False

    def __init__(self, module: Any):
        self.module = module

    def to(self, device: Any) -> ModuleGenerator:
        """The module on ``device`` in eval mode."""
        self.module = self.module.to(device).eval()
        return self

    def read_source(self, path: Path, joint_map: str | None = None) -> Any:
        raise UsageError(f"a {self.generation_card().family} checkpoint takes no source motion")

    def option(self, key: str, value: str) -> Any:
        """The value of family option ``key`` given as text (``--option KEY=VALUE``), checked: a number within
        its range where the card gives one (``GenerationCard.option_ranges``), else the text."""
        bounds = self.generation_card().option_ranges.get(key)
        return value if bounds is None else bounds.read(key, value)

    def with_prior(self, prior: Any) -> None:
        """Draw from ``prior``, a second checkpoint's module (``--prior_ckpt``), where ``takes_prior``."""
        raise UsageError(f"--prior_ckpt: a {self.generation_card().family} checkpoint takes no prior checkpoint")


def check_request(card: GenerationCard, request: GenerationRequest, what: str = "this checkpoint") -> None:
    """A request the card can answer, or one line saying what is wrong, before anything is sampled.
    ``what`` names the model in the message (its file and class)."""
    if request.timeline is not None:
        check_timeline_request(card, request, what)
    given = {"text": bool(request.prompts) or request.timeline is not None,
             "motion": request.source is not None or request.source_module is not None,
             "species": request.species is not None}
    if given["text"] and "text" not in card.inputs and "unconditional" in card.inputs:
        raise UsageError(f"{what} is an unconditional pretraining checkpoint: it samples without a condition; pass "
                         "--unconditional, or a text-conditioned checkpoint for prompts")
    for name in ("text", "motion", "species"):
        if given[name] and name not in card.inputs:
            raise UsageError(f"{what} does not generate from {_WHAT[name]}; it takes {card_inputs(card)}")
    if not given["text"] and not given["motion"] and "unconditional" not in card.inputs:
        raise UsageError(f"{what} generates from {card_inputs(card)}: give them")
    for name in card.needs:
        if not given[name]:
            raise UsageError(f"{what} needs {_WHAT[name]}")
    if request.source_module is not None:
        if not card.source_generator:
            raise UsageError(f"{what} takes no second checkpoint to make its source motion")
        source = request.source_module.generation_card()
        if "text" not in source.inputs:
            raise UsageError(f"the source-motion checkpoint generates from {card_inputs(source)}, not from prompts")
    if not card.min_frames <= request.frames <= card.max_frames:
        raise UsageError(f"--length must give {card.min_frames}..{card.max_frames} frames at {card.fps:g} fps, got "
                         f"{request.frames}")
    if request.steps is not None and card.max_steps and not 1 <= request.steps <= card.max_steps:
        raise UsageError(f"--steps must be in 1..{card.max_steps} (the checkpoint's diffusion steps), got "
                         f"{request.steps}")
    if request.sampler is not None and not card.samplers:
        raise UsageError(f"--sampler: {what} has no sampler to choose")
    refuse_unknown_options(card, request.options, what)
    if request.control is not None:
        if not card.constraints:
            raise UsageError(f"{what} takes no constraints (its generation card lists none)")
        if request.control.frames != request.frames:
            raise ValueError(f"constraints resolved for {request.control.frames} frames, {request.frames} asked")
    if request.species is not None and not card.open_species and request.species not in card.species:
        known = ", ".join(card.species) or "none (train the model first)"
        raise UsageError(f"unknown animal {request.species!r}; this checkpoint knows: {known}")


def check_timeline_request(card: GenerationCard, request: GenerationRequest, what: str) -> None:
    """One line when the card takes no timeline of this kind, prompts come with it, or it does not fit the
    request's motion (``TimelineFile.check``)."""
    if missing := [kind for kind in request.timeline.kinds if kind not in card.timeline]:
        takes = f"it takes {' and '.join(card.timeline)} only" if card.timeline else "its card lists none"
        name = {"timeline": "prompt timeline", "parts": "body-part composition"}[missing[0]]
        raise UsageError(f"--timeline: {what} takes no {name}; {takes}")
    if request.prompts:
        raise UsageError("give prompts or --timeline (whose segments carry their texts), not both")
    request.timeline.check(card.skeleton, request.frames / card.fps, card.fps)


def card_inputs(card: GenerationCard) -> str:
    """What a card generates from, in words."""
    return " and ".join(_WHAT[i] for i in card.inputs if i != "unconditional") or _WHAT["unconditional"]


_WHAT = {"text": "prompts", "unconditional": "nothing (--unconditional)", "motion": "a source motion (--from_motion)",
         "species": "a species (--animal)"}


def parse_options(generator: Generator, pairs: list[str], what: str = "this checkpoint") -> dict[str, Any]:
    """``--option KEY=VALUE`` pairs as the family options of ``generator``'s card, each value read by its
    ``option``; a key the card does not list is one line naming the card's options."""
    card, options = generator.generation_card(), {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            example = next(iter(card.options), "KEY")
            raise UsageError(f"--option {pair!r}: give KEY=VALUE, e.g. --option {example}=VALUE")
        refuse_unknown_options(card, [key], what)
        options[key] = generator.option(key, value)
    return options


def refuse_unknown_options(card: GenerationCard, keys: Any, what: str) -> None:
    """One line naming the card's options when ``keys`` holds one the card does not list."""
    if unknown := sorted(set(keys) - set(card.options)):
        takes = ", ".join(card.options) or "none"
        raise UsageError(f"{what} takes no option {', '.join(unknown)}; its options: {takes}")


def number_option(key: str, value: str, low: float, high: float, low_open: bool = False) -> float:
    """``value`` as a number in [low, high] (``low_open``: (low, high]), else one line naming ``key``."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number) or not (low < number if low_open else low <= number) or not number <= high:
        bounds = f"{'(' if low_open else '['}{low:g}, {high:g}]"
        raise UsageError(f"--option {key}={value}: give a number in {bounds}")
    return number
