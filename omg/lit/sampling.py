"""The tensor-level sampler a generative LightningModule declares, and how it samples.

``Sampler.sample(texts, lengths, settings)`` is what the evaluation and render callbacks, ``omg
bench`` and the OMG → animal chain (OmniMotionGPT's human source) call: motions (B, max(lengths), D)
un-normalised in the module's representation. ``SamplingSettings`` carries every way of sampling in
one frozen value, checked once when it is made. Generation from files and requests (the card, reading
and writing) sits a floor up, in ``omg.generation``; this protocol lives with the modules because the
training callbacks call it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from omg.errors import UsageError
from omg.lit.timeline import Timeline
from omg.registry import MODULE_SAMPLERS, SAMPLERS

if TYPE_CHECKING:
    from omg.lit.control import Control


MAX_STANCE_ROOT = 1.0  # the whole step of the root by the stance foot


def check_stance_root(strength: float, key: str) -> float:
    """``strength`` when it is in [0, ``MAX_STANCE_ROOT``] (0: off), else one line naming ``key``: the one range
    check of the module's, a callback's and a sampling call's stance_root."""
    if not 0 <= strength <= MAX_STANCE_ROOT:
        raise UsageError(f"{key} must be in [0, {MAX_STANCE_ROOT:g}] (0: off), got {strength!r}")
    return float(strength)


MAX_SMOOTHING = 10.0  # frames: half a second at 20 fps, past which a gesture itself is smoothed away


def check_smoothing(sigma: float, key: str) -> float:
    """``sigma`` (frames) when it is a number in [0, ``MAX_SMOOTHING``] (0: off), else one line naming ``key``."""
    if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not 0 <= sigma <= MAX_SMOOTHING:
        raise UsageError(f"{key} must be a number of frames in [0, {MAX_SMOOTHING:g}] (0: off), got {sigma!r}")
    return float(sigma)


@dataclass(frozen=True)
class SamplingDefaults:
    """A diffusion module's own sampling defaults (``model.init_args.sampling``), kept in its checkpoint: what
    ``sample`` uses where ``SamplingSettings`` leave them unset (None). Both are omg's, not OMG's (0: off).

    ``stance_root`` in [0, ``MAX_STANCE_ROOT``]: step the root of each denoised estimate by its stance foot
    (``MotionDiffusionModule.stance_denoiser``); ``smoothing`` in [0, ``MAX_SMOOTHING``] frames: smooth each
    denoised estimate over time by a Gaussian of that sigma (``omg.lit.control.smoothed``)."""

    stance_root: float = 0.0
    smoothing: float = 0.0


@dataclass(frozen=True)
class SamplingSettings:
    """How a ``Sampler`` samples.

    ``steps`` of the registered ``sampler`` (``omg.samplers``: ddim, dpmpp, euler); ``guidance`` the
    classifier-free guidance scale (None: the module's); ``seed`` fixes the initial noise, or ``seeds``
    (one per motion) each motion's own; ``use_ema``: the EMA weights where kept; ``stance_root`` (None:
    the module's) steps the root of every denoised estimate by its stance foot; ``autocast`` (a torch
    dtype) runs the network under autocast; ``compile`` runs it through ``torch.compile``; ``control``
    (``omg.lit.control.Control``, None: none) steers every denoised estimate towards joint targets. ``key`` names
    the settings in the one-line errors (``EvalCallback``); a family takes the settings that apply to it
    (OmniMotionGPT passes steps, sampler and guidance to its human generator). ``timeline``
    (``omg.lit.timeline.Timeline``): every motion follows its texts, by stretches of frames and by body
    parts, sampled with ``texts=None`` (a text-conditioned module's). ``smoothing`` (frames, 0: off; None: the
    module's) smooths every denoised estimate over time by a Gaussian of that sigma (``omg.lit.control.smoothed``):
    the frame-to-frame shake of a guided sample."""

    steps: int = 200
    sampler: str = "ddim"
    guidance: float | None = None
    seed: int = 0
    seeds: tuple[int, ...] | None = None
    use_ema: bool = True
    stance_root: float | None = None
    autocast: torch.dtype | None = None
    compile: bool = False
    control: Control | None = None
    key: str = ""
    timeline: Timeline | None = None
    smoothing: float | None = None

    def __post_init__(self) -> None:
        where = f"{self.key}." if self.key else ""
        if isinstance(self.steps, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise UsageError(f"{where}steps must be an integer >= 1, got {self.steps!r}")
        SAMPLERS.get(self.sampler)  # an unknown name is one line naming the known ones
        if self.stance_root is not None:
            object.__setattr__(self, "stance_root", check_stance_root(self.stance_root, f"{where}stance_root"))
        if self.smoothing is not None:
            object.__setattr__(self, "smoothing", check_smoothing(self.smoothing, f"{where}smoothing"))
        if self.seeds is not None:
            object.__setattr__(self, "seeds", tuple(int(s) for s in self.seeds))

    def report(self) -> dict[str, Any]:
        """What an evaluation report records: steps, guidance, use_ema, sampler, and stance_root, smoothing and
        the constraints' names when set."""
        shown = {"steps": self.steps, "guidance": self.guidance, "use_ema": self.use_ema, "sampler": self.sampler}
        if self.control is not None:
            shown["control"] = list(self.control.names)
        if self.smoothing:
            shown["smoothing"] = self.smoothing
        return shown if self.stance_root is None else {**shown, "stance_root": self.stance_root}


@runtime_checkable
class Sampler(Protocol):
    """A LightningModule that samples motion: ``text_conditional`` says whether ``sample`` follows texts
    (None samples without them); ``check_sampling`` refuses, in one line naming ``key``, settings this
    module cannot sample with."""

    text_conditional: bool

    def sample(self, texts: Sequence[str] | None, lengths: Tensor | Sequence[int],
               settings: SamplingSettings | None = None) -> Tensor: ...

    def check_sampling(self, settings: SamplingSettings, key: str) -> None: ...


def sampler_of(module: Any, key: str) -> Sampler:
    """``module`` when it declares the ``Sampler`` protocol, else the sampler registered for its class
    (``MODULE_SAMPLERS``: OmniMotionGPT's composes the module with its human source), else one line naming
    ``key`` and the module."""
    if isinstance(module, Sampler):
        return module
    if (sampler := MODULE_SAMPLERS.for_class(type(module))) is None:
        raise UsageError(f"{key} needs a model that samples motion (omg.lit.sampling.Sampler: sample(texts, lengths, "
                         f"settings)); {type(module).__name__} has none")
    return sampler(module)
