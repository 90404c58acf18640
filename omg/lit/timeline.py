"""Prompt timelines and body-part composition at sampling time: one continuous motion whose stretches of
frames, and whose body parts, each follow their own text.

At every sampling step the text-conditioned denoiser runs once per distinct text over the whole sequence
(the texts batched together), and the denoised estimates x̂0 are blended frame by frame and feature by
feature (DiffCollage / FlowMDM): ``x̂0 = Σ_k W_k ⊙ x̂0_k`` with weights ``W`` (K, T, D) that sum to 1 over
the texts. Where two segments of a timeline meet, the weights cross over smoothly (a smoothstep over the
overlap, or over ``transition`` seconds centred on the boundary where they only touch), so every step moves
the whole sequence towards one motion that changes from one text to the next; a body part takes the features
of its joints (``Representation.channel_joints``: the root's features carry the trajectory) from its own
text. Away from every crossing a frame's estimate is its own text's alone. With windows (a file's
``context``) each text's pass sees only its own frames and that much on either side (``text_estimates``).

With ``chains="separate"`` each text keeps its own sampling chain instead (SINC's splice, coupled): the
sampler's state is K chains of the B motions (K·B rows, all starting from the same noise), chain k denoised
by text k alone, reading its own estimate of every part, so a walk's pass denoises a walking body, not the
walk's legs under another text's waving arms. At every step the chains' estimates are joined by the same
weights (the composed x̂0) and each chain's estimate is pulled towards it by ``coupling`` (0: the chains
independent, each exactly its text sampled alone; 1: every chain given the composed estimate, the joint
blend above); the motion returned is the chains' samples joined by the weights (``compose_chains``). With
windows, chain k's text denoises only its window of the chain; inside it the chain's estimate is pulled towards
the composed one as above, outside it the chain carries the composed estimate (``chains_denoiser``).

``resolve_timeline`` turns seconds and body-part names into the tensor-level ``Timeline`` that
``SamplingSettings.timeline`` carries; reading and checking a user's file is ``omg.generation.timeline``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from omg.diffusion import Denoiser
from omg.errors import UsageError
from omg.motion.base import Representation
from omg.skeleton import body_parts

CHAINS = ("joint", "separate")  # a timeline's sampling: one chain of blended estimates, or one chain per text
# separate chains' pull towards the composed estimate: on the small recipe's compositions 0 and 0.1 passed both
# parts alike (6/8) and 0.5 fell back to the joint blend's 2/8; 0.1 skated less (docs/results/timelines.md)
DEFAULT_COUPLING = 0.1


@dataclass(frozen=True)
class Segment:
    """A stretch of the motion, ``start`` to ``end`` seconds, that follows ``text``."""

    start: float
    end: float
    text: str


@dataclass(frozen=True)
class PartText:
    """Body ``parts`` (names of ``omg.skeleton.body_parts``) that follow ``text``, from ``start`` to ``end``
    seconds (None: the whole motion)."""

    parts: tuple[str, ...]
    text: str
    start: float | None = None
    end: float | None = None


@dataclass(frozen=True, eq=False)
class Timeline:
    """What a sampler blends: ``texts`` (K distinct captions) and ``weights`` (K, T, D), the share of text k's
    denoised estimate in each feature of each frame; they sum to 1 over the texts everywhere. ``windows``: the
    frames [start, end) each text's denoiser sees (None: every text sees the whole sequence; with separate
    chains, of its own chain); a window holds every frame its text has a share in. ``chains``: ``joint`` (one
    chain, the texts' estimates blended) or ``separate`` (one chain per text, each pulled towards the blend by
    ``coupling`` in [0, 1]; the module docstring)."""

    texts: tuple[str, ...]
    weights: Tensor  # (K, T, D)
    windows: tuple[tuple[int, int], ...] | None = None
    chains: str = "joint"
    coupling: float = DEFAULT_COUPLING

    def __post_init__(self) -> None:
        if self.chains not in CHAINS:
            raise ValueError(f"timeline chains {self.chains!r}; one of {', '.join(CHAINS)}")
        if not 0.0 <= self.coupling <= 1.0:
            raise ValueError(f"timeline coupling {self.coupling!r} outside [0, 1]")
        w = self.weights
        if w.ndim != 3 or w.shape[0] != len(self.texts) or not self.texts:
            raise ValueError(f"timeline weights (K, T, D) for {len(self.texts)} texts, got {tuple(w.shape)}")
        if not torch.isfinite(w).all() or not torch.allclose(w.sum(0), torch.ones_like(w[0]), atol=1e-5):
            raise ValueError("timeline weights must be finite and sum to 1 over the texts")
        if self.windows is not None:
            if len(self.windows) != len(self.texts):
                raise ValueError(f"{len(self.windows)} windows for {len(self.texts)} texts")
            frames = torch.arange(w.shape[1])
            for (start, end), share in zip(self.windows, w):
                inside = (frames >= start) & (frames < end)
                if not 0 <= start < end <= w.shape[1] or (share.abs().sum(-1)[~inside] > 0).any():
                    raise ValueError(f"a window {start}..{end} of {w.shape[1]} frames must hold its text's frames")

    @property
    def separate(self) -> bool:
        """Whether each text samples its own chain (K·B rows in the sampler)."""
        return self.chains == "separate"


def smoothstep(u: Tensor) -> Tensor:
    """3u² − 2u³ on u clamped to [0, 1]: 0 → 1 with zero slope at both ends."""
    u = u.clamp(0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _crossing(times: Tensor, start: float, end: float) -> Tensor:
    """(T,) 0 before ``start``, 1 after ``end``, a smoothstep between (a step at ``start`` when end == start)."""
    if end <= start:
        return (times >= start).to(times.dtype)
    return smoothstep((times - start) / (end - start))


def segment_weights(segments: Sequence[Segment], times: Tensor, transition: float) -> Tensor:
    """(S, T) each segment's share of each frame: 1 inside it, crossing smoothly to its neighbour over their
    overlap, or over ``transition`` seconds centred on the boundary where they only touch (or overlap less);
    normalised over the segments. ``segments`` in time order, with no gap between neighbours."""
    weights = torch.ones(len(segments), len(times), dtype=times.dtype)
    for i in range(len(segments) - 1):
        a, b = segments[i], segments[i + 1]
        centre, half = (b.start + a.end) / 2, max(a.end - b.start, transition) / 2
        rise = _crossing(times, centre - half, centre + half)
        weights[i] *= 1.0 - rise
        weights[i + 1] *= rise
    total = weights.sum(0)
    if (total <= 0).any():  # crossings of a segment shorter than them meet: its own frames are its own
        inside = torch.stack([(times >= s.start) & (times <= s.end) for s in segments]).to(times.dtype)
        weights = torch.where(total > 0, weights, inside)
        total = weights.sum(0)
    return weights / total


def part_window(part: PartText, times: Tensor, seconds: float, transition: float) -> Tensor:
    """(T,) 1 while ``part`` holds (its start to its end, the whole motion without them), crossing in and
    out over ``transition`` seconds centred on its start and end (none at the motion's own ends)."""
    start, end = part.start or 0.0, seconds if part.end is None else part.end
    window = torch.ones_like(times)
    if start > 0:
        window = window * _crossing(times, start - transition / 2, start + transition / 2)
    if end < seconds:
        window = window * (1.0 - _crossing(times, end - transition / 2, end + transition / 2))
    return window


def text_windows(weights: Tensor, context: int) -> tuple[tuple[int, int], ...]:
    """(K, T, D) shares -> each text's frames [start, end): from its first frame with a share to its last,
    widened by ``context`` frames on each side within the motion."""
    frames = weights.shape[1]
    windows = []
    for share in weights.abs().sum(-1) > 0:  # (T,) the frames this text has a share in
        held = torch.nonzero(share).flatten()
        windows.append((max(0, int(held[0]) - context), min(frames, int(held[-1]) + 1 + context)))
    return tuple(windows)


def resolve_timeline(segments: Sequence[Segment], parts: Sequence[PartText], frames: int, fps: float,
                     representation: Representation, transition: float = 0.5,
                     context: float | None = None, chains: str = "joint",
                     coupling: float = DEFAULT_COUPLING) -> Timeline:
    """The ``Timeline`` of ``frames`` feature frames at ``fps`` for a model of ``representation``: the segments
    (in time order, meeting or overlapping) share the frames, then each ``PartText`` in turn takes its joints'
    features (``channel_joints``) while it holds. Without segments, the first part's text is the base the
    others replace. ``context`` (seconds; None: the whole motion) limits what each text's denoiser sees to
    its own frames and that much on either side (``text_windows``). The checks of a user's values (times
    inside the motion, known part names) are ``omg.generation.timeline``'s; ``body_parts`` and
    ``channel_joints`` raise their own one line. ``chains`` and ``coupling``: ``Timeline``'s."""
    times = torch.arange(frames, dtype=torch.float64) / fps  # (T,) the time of each feature frame
    dim = representation.dim
    texts = list(dict.fromkeys([s.text for s in segments] + [p.text for p in parts]))
    weights = torch.zeros(len(texts), frames, dim, dtype=torch.float64)  # (K, T, D)
    if segments:
        for segment, share in zip(segments, segment_weights(segments, times, transition)):
            weights[texts.index(segment.text)] += share[:, None]
    else:
        weights[texts.index(parts[0].text)] = 1.0
    if parts:
        named = body_parts(representation.skeleton)
        channel_joints = torch.as_tensor(representation.channel_joints())  # (D,)
        seconds = frames / fps
        for part in parts:
            joints = torch.tensor(sorted({j for name in part.parts for j in named[name]}))
            channels = torch.isin(channel_joints, joints).to(weights.dtype)  # (D,)
            take = part_window(part, times, seconds, transition)[:, None] * channels  # (T, D)
            own = torch.zeros(len(texts), 1, 1, dtype=weights.dtype)
            own[texts.index(part.text)] = 1.0
            weights = weights * (1.0 - take) + own * take
    weights = weights.float()
    windows = None if context is None else text_windows(weights, round(context * fps))
    return Timeline(tuple(texts), weights, windows, chains, coupling)


TextDenoiser = Callable[[Sequence[str], Tensor, "float | None"], Denoiser]  # (texts, mask, guidance) -> denoiser
TextEstimates = Callable[[Tensor, Tensor], Tensor]  # (K·B rows x_t, t) -> (K, B, T, D) each text's x̂0 of its rows


def join(estimates: Tensor, weights: Tensor) -> Tensor:
    """(K, B, T, D) each text's estimate (or each chain's sample) -> (B, T, D): each feature of each frame from
    the texts by ``weights`` (K, 1, T, D), the timeline's shares. The joint blend, the separate chains' composed
    estimate and their returned motion are all this join."""
    return (weights.to(device=estimates.device, dtype=estimates.dtype) * estimates).sum(0)


def text_estimates(denoiser: TextDenoiser, timeline: Timeline, mask: Tensor, guidance: float | None) -> TextEstimates:
    """Each text's x̂0 of its own K·B rows (text k's at rows k·B..(k+1)·B, ``mask`` (B, T) the motions' real
    frames), the K texts in one denoiser call. With ``timeline.windows`` text k's denoiser sees only its window
    of its rows: frames start..end cut out and moved to the start of a row of the longest window's length, so a
    text cannot read another text's stretch of the motion (a run 6 s later) into its own, and the K passes cost
    their windows' frames instead of K whole sequences; its estimate is 0 outside the window, where it has no
    share."""
    k, (b, frames) = len(timeline.texts), mask.shape
    if timeline.weights.shape[1] != frames:
        raise ValueError(f"a timeline of {timeline.weights.shape[1]} frames for motions of {frames}")
    texts = [text for text in timeline.texts for _ in range(b)]
    windows = timeline.windows
    if windows is None:
        denoise = denoiser(texts, mask.repeat(k, 1), guidance)
        return lambda x, t: denoise(x, t).unflatten(0, (k, b))
    denoise = denoiser(texts, window_mask(mask, windows), guidance)
    length = max(end - start for start, end in windows)

    def windowed(x: Tensor, t: Tensor) -> Tensor:
        rows = x.unflatten(0, (k, b))  # (K, B, T, D)
        cut = x.new_zeros(k, b, length, x.shape[-1])  # (K, B, L, D)
        for i, (start, end) in enumerate(windows):
            cut[i, :, :end - start] = rows[i, :, start:end]
        estimates = denoise(cut.flatten(0, 1), t).unflatten(0, (k, b))  # (K, B, L, D)
        x0 = torch.zeros_like(rows)
        for i, (start, end) in enumerate(windows):
            x0[i, :, start:end] = estimates[i, :, :end - start]
        return x0

    return windowed


def timeline_denoiser(denoiser: TextDenoiser, timeline: Timeline, mask: Tensor, guidance: float | None) -> Denoiser:
    """The blended x̂0 of ``timeline`` for a batch of B motions (``mask`` (B, T)), each following the whole
    timeline: ``denoiser`` (a module's ``denoiser(texts, mask, guidance)``: guidance as it does it) runs once
    per step on the K texts' copies of the batch, batched as K·B rows (over their windows with ``context``)."""
    k = len(timeline.texts)
    estimates = text_estimates(denoiser, timeline, mask, guidance)
    weights = timeline.weights.to(mask.device)[:, None]  # (K, 1, T, D)

    def blended(x: Tensor, t: Tensor) -> Tensor:
        return join(estimates(x.repeat(k, 1, 1), t.repeat(k)), weights)

    return blended


def chains_denoiser(denoiser: TextDenoiser, timeline: Timeline, mask: Tensor, guidance: float | None) -> Denoiser:
    """Separate chains (the module docstring): x (K·B rows, chain k of motion b at row k·B + b) -> each chain's
    x̂0, its own text's estimate pulled towards the composed one by ``timeline.coupling``. ``denoiser`` runs
    once per step on the K·B rows, each with its chain's text (with ``context``, over the chain's own window);
    ``mask`` (B, T) the motions' real frames. Outside its window a chain has no estimate of its own: it carries
    the composed one there, frames that have no share in the motion but that ``stance_root`` and spatial
    control read as the rest of the chain's body."""
    estimates = text_estimates(denoiser, timeline, mask, guidance)
    weights = timeline.weights.to(mask.device)[:, None]  # (K, 1, T, D)
    inside = None
    if timeline.windows is not None:
        frames = torch.arange(mask.shape[1], device=mask.device)
        inside = torch.stack([(frames >= start) & (frames < end) for start, end in timeline.windows])  # (K, T)
        inside = inside[:, None, :, None]  # (K, 1, T, 1)
    coupling = timeline.coupling

    def chained(x: Tensor, t: Tensor) -> Tensor:
        x0 = estimates(x, t)  # (K, B, T, D) each chain by its own text
        composed = join(x0, weights)  # (B, T, D) each part from its own text's chain
        if inside is not None:
            x0 = torch.where(inside, x0, composed)
        # lerp is exact at both ends: 0 leaves a chain its own estimate, 1 gives it the composed one
        return torch.lerp(x0, composed.expand_as(x0), coupling).flatten(0, 1)

    return chained


def compose_chains(x: Tensor, timeline: Timeline) -> Tensor:
    """(K·B, T, D) the separate chains' samples -> (B, T, D) the motion: each feature of each frame from its
    texts' chains by the timeline's weights."""
    return join(x.unflatten(0, (len(timeline.texts), -1)), timeline.weights[:, None])


def window_mask(mask: Tensor, windows: Sequence[tuple[int, int]]) -> Tensor:
    """(B, T) real frames -> (K·B, L) the real frames of each text's window, moved to its start, L the longest
    window: text k's rows are k·B..(k+1)·B."""
    length = max(end - start for start, end in windows)
    out = mask.new_zeros(len(windows), *mask.shape[:1], length)  # (K, B, L)
    for k, (start, end) in enumerate(windows):
        out[k, :, :end - start] = mask[:, start:end]
    return out.flatten(0, 1)


def check_timeline(timeline: Timeline, text_conditional: bool, dim: int, module: str) -> None:
    """One line when a module cannot sample ``timeline``: an unconditional one, or features of another size."""
    if not text_conditional:
        raise UsageError(f"{module} is unconditional: a prompt timeline needs a text-conditioned model")
    if timeline.weights.shape[2] != dim:
        raise ValueError(f"a timeline of {timeline.weights.shape[2]} features for a model of {dim}")

