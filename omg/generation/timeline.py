"""A user's timeline (``omg generate --timeline FILE.json``, the API's ``timeline``): a prompt timeline and
body-part composition, read and checked here, one line per error, before anything is sampled or written
(docs/guide/timelines.md). Its sampling is ``omg.lit.timeline``.

The file is JSON: a list of segments ``[{"start": s, "end": s, "text": ...}, ...]`` (seconds), or a mapping
``{"timeline": [...], "parts": [{"parts": [...], "text": ..., "start"?: s, "end"?: s}, ...],
"transition"?: s, "context"?: s, "chains"?: "joint" | "separate", "coupling"?: 0..1}``. Segments come in time
order, the first at 0 s, each meeting or overlapping the next (no gap, none inside another, none of zero length);
the last one ends the motion. Body parts are named
by ``omg.skeleton.body_parts`` of the model's skeleton, and two entries never name one joint at the same time.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omg.errors import UsageError
from omg.files import read_text
from omg.generation.protocol import NumberRange
from omg.lit.timeline import CHAINS, DEFAULT_COUPLING, PartText, Segment, Timeline, resolve_timeline
from omg.motion.base import Representation
from omg.skeleton import body_parts, get_skeleton

DEFAULT_TRANSITION = 0.5  # seconds two segments that only touch cross over in
MAX_ENTRIES = 32  # segments and parts in one file: each distinct text is one more denoiser pass per step
SEGMENT_KEYS = ("start", "end", "text")
PART_KEYS = ("parts", "text", "start", "end")
# the numbers a timeline file may give (seconds; coupling a weight), with their bounds and defaults (context None:
# the whole motion): ``parse_timeline`` reads the file by them, ``GET /v1/models`` lists them for the page
TIMELINE_RANGES = {"transition": NumberRange(0.0, default=DEFAULT_TRANSITION), "context": NumberRange(0.0),
                   "coupling": NumberRange(0.0, 1.0, default=DEFAULT_COUPLING)}


@dataclass(frozen=True)
class TimelineFile:
    """A checked timeline in seconds: ``segments`` in time order, ``parts`` in the file's order, ``transition``
    seconds of crossing where two segments only touch (and at a part's start and end), ``context`` seconds
    each text's denoiser sees on either side of its own frames (None: the whole motion); ``chains`` and
    ``coupling``: one sampling chain of blended estimates, or one per text pulled towards the blend
    (``omg.lit.timeline``)."""

    segments: tuple[Segment, ...] = ()
    parts: tuple[PartText, ...] = ()
    transition: float = DEFAULT_TRANSITION
    context: float | None = None
    chains: str = "joint"
    coupling: float = DEFAULT_COUPLING

    @property
    def end(self) -> float | None:
        """The end of the last segment, the motion's length; None without segments."""
        return self.segments[-1].end if self.segments else None

    @property
    def kinds(self) -> tuple[str, ...]:
        """What the file holds, as a generation card lists it: ``timeline``, ``parts``."""
        return (("timeline",) if self.segments else ()) + (("parts",) if self.parts else ())

    def texts(self) -> list[str]:
        return list(dict.fromkeys([s.text for s in self.segments] + [p.text for p in self.parts]))

    def to_dict(self) -> dict[str, Any]:
        """The file as ``generation.json`` records it."""
        return {"timeline": [{"start": s.start, "end": s.end, "text": s.text} for s in self.segments],
                "parts": [{"parts": list(p.parts), "text": p.text,
                           **({} if p.start is None else {"start": p.start}),
                           **({} if p.end is None else {"end": p.end})} for p in self.parts],
                "transition": self.transition, **({} if self.context is None else {"context": self.context}),
                **({"chains": self.chains, "coupling": self.coupling} if self.chains != "joint" else {})}

    def check(self, skeleton: str, seconds: float, fps: float, where: str = "--timeline") -> None:
        """One line when the file does not fit a motion of ``seconds`` at ``fps`` on ``skeleton``: a segment
        or part outside the motion, a last segment that ends before it (a gap), a body part the skeleton has
        not, two parts on one joint at once."""
        half = 0.5 / fps  # a frame's rounding
        for i, s in enumerate(self.segments):
            if s.end > seconds + half:
                raise UsageError(f"{where}: timeline[{i}] ends at {s.end:g} s, after the motion's end ({seconds:g} s)")
        if self.end is not None and self.end < seconds - half:
            raise UsageError(f"{where}: the timeline ends at {self.end:g} s, before the motion's end ({seconds:g} s): "
                             f"a gap; extend the last segment or give a length of {self.end:g} s")
        named = body_parts(get_skeleton(skeleton))
        for i, p in enumerate(self.parts):
            if p.end is not None and p.end > seconds + half:
                raise UsageError(f"{where}: parts[{i}] ends at {p.end:g} s, after the motion's end ({seconds:g} s)")
            if p.start is not None and p.start >= seconds:
                raise UsageError(f"{where}: parts[{i}] starts at {p.start:g} s, after the motion's end "
                                 f"({seconds:g} s)")
            for name in p.parts:
                if name not in named:
                    raise UsageError(f"{where}: parts[{i}]: unknown body part {name!r}; {skeleton}'s: "
                                     f"{', '.join(named)}")
        for i, p in enumerate(self.parts):
            for j, q in enumerate(self.parts[:i]):
                shared = {k for n in p.parts for k in named[n]} & {k for n in q.parts for k in named[n]}
                if shared and _overlap(p, q, seconds):
                    joint = get_skeleton(skeleton).names[min(shared)]
                    raise UsageError(f"{where}: parts[{j}] and parts[{i}] both move {joint} at the same time; give "
                                     "each joint one text at a time")

    def resolve(self, frames: int, fps: float, representation: Representation) -> Timeline:
        """The tensor-level timeline of ``frames`` feature frames (``omg.lit.timeline.resolve_timeline``)."""
        return resolve_timeline(self.segments, self.parts, frames, fps, representation, self.transition,
                                self.context, self.chains, self.coupling)


def _overlap(p: PartText, q: PartText, seconds: float) -> bool:
    a0, a1 = p.start or 0.0, seconds if p.end is None else p.end
    b0, b1 = q.start or 0.0, seconds if q.end is None else q.end
    return a0 < b1 and b0 < a1


def read_timeline(path: str | Path, check_text: Callable[[str, str], str] | None = None) -> TimelineFile:
    """The ``--timeline`` file at ``path`` (JSON), checked (``parse_timeline``)."""
    where = f"--timeline {path}"
    text = read_text(path, "--timeline")
    try:
        data = json.loads(text)
    except ValueError as e:
        raise UsageError(f"{where}: not valid JSON ({e})") from None
    return parse_timeline(data, where, check_text)


def parse_timeline(data: Any, where: str = "timeline",
                   check_text: Callable[[str, str], str] | None = None) -> TimelineFile:
    """A timeline from its JSON value (the module docstring), every entry checked here; ``where`` names it in
    the one-line errors; ``check_text(text, what)`` checks each text as a prompt is (its plain-text check)."""
    if isinstance(data, list):
        data = {"timeline": data}
    if not isinstance(data, dict):
        raise UsageError(f"{where}: expected a list of segments [{{\"start\", \"end\", \"text\"}}] or "
                         "{\"timeline\": [...], \"parts\": [...]}")
    if extra := sorted(set(data) - {"timeline", "parts", "transition", "context", "chains", "coupling"}):
        raise UsageError(f"{where}: unknown key {extra[0]!r}; a timeline file has timeline, parts, transition, "
                         "context, chains, coupling")
    raw_segments, raw_parts = data.get("timeline") or [], data.get("parts") or []
    for key, value in (("timeline", raw_segments), ("parts", raw_parts)):
        if not isinstance(value, list):
            raise UsageError(f"{where}: {key} must be a list, got {type(value).__name__}")
    if not raw_segments and not raw_parts:
        raise UsageError(f"{where}: no segments and no parts; give a timeline [{{\"start\": 0, \"end\": 3, "
                         "\"text\": \"a person walks forward\"}, ...] or parts")
    if len(raw_segments) + len(raw_parts) > MAX_ENTRIES:
        raise UsageError(f"{where}: {len(raw_segments) + len(raw_parts)} entries; at most {MAX_ENTRIES}")
    transition = _seconds(data.get("transition", DEFAULT_TRANSITION), f"{where}: transition")
    context = None if data.get("context") is None else _seconds(data["context"], f"{where}: context")
    chains = check_chains(data.get("chains", "joint"), f"{where}: chains")
    coupling, bounds = data.get("coupling", DEFAULT_COUPLING), TIMELINE_RANGES["coupling"]
    if isinstance(coupling, bool) or not isinstance(coupling, int | float) or \
            not bounds.low <= coupling <= bounds.high:
        raise UsageError(f"{where}: coupling must be a number in [{bounds.low:g}, {bounds.high:g}], got {coupling!r}")
    if "coupling" in data and chains != "separate":
        raise UsageError(f"{where}: coupling pulls separate chains together; give it with \"chains\": \"separate\"")
    segments = tuple(_segment(s, f"{where}: timeline[{i}]", check_text) for i, s in enumerate(raw_segments))
    for i, (a, b) in enumerate(zip(segments, segments[1:])):
        if b.start < a.start:
            raise UsageError(f"{where}: timeline[{i + 1}] starts at {b.start:g} s, before timeline[{i}] "
                             f"({a.start:g} s); list the segments in time order")
        if b.start > a.end:
            raise UsageError(f"{where}: a gap between timeline[{i}] (ends at {a.end:g} s) and timeline[{i + 1}] "
                             f"(starts at {b.start:g} s); let each segment meet or overlap the next")
        if b.end <= a.end:
            raise UsageError(f"{where}: timeline[{i + 1}] ({b.start:g}..{b.end:g} s) lies inside timeline[{i}] "
                             f"({a.start:g}..{a.end:g} s); a segment must end after the one before it")
    if segments and segments[0].start > 0:
        raise UsageError(f"{where}: timeline[0] starts at {segments[0].start:g} s; the timeline starts the motion, "
                         "at 0 s (a gap before it)")
    parts = tuple(_part(p, f"{where}: parts[{i}]", check_text) for i, p in enumerate(raw_parts))
    return TimelineFile(segments, parts, transition, context, chains, float(coupling))


def check_chains(value: Any, where: str) -> str:
    """``value`` when it names a way of sampling a timeline's texts (``CHAINS``), else one line naming ``where``."""
    if value not in CHAINS:
        raise UsageError(f"{where} must be one of {', '.join(CHAINS)}, got {value!r}")
    return value


def _fields(entry: Any, keys: tuple[str, ...], needed: tuple[str, ...], what: str, where: str) -> dict[str, Any]:
    if not isinstance(entry, dict):
        raise UsageError(f"{where}: expected a mapping {{{', '.join(keys)}}}, got {type(entry).__name__}")
    if extra := sorted(set(entry) - set(keys)):
        raise UsageError(f"{where}: unknown key {extra[0]!r}; {what} has {', '.join(keys)}")
    if missing := [k for k in needed if k not in entry]:
        raise UsageError(f"{where}: missing {missing[0]!r}; {what} has {', '.join(keys)}")
    return entry


def _seconds(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise UsageError(f"{where} must be a finite number of seconds >= 0, got {value!r}")
    return float(value)


def _text(value: Any, where: str, check_text: Callable[[str, str], str] | None) -> str:
    if not isinstance(value, str) or not value.strip():
        raise UsageError(f"{where}.text must be a non-empty sentence, got {value!r}")
    return check_text(value, f"{where}.text") if check_text is not None else value


def _span(entry: dict, where: str, required: bool) -> tuple[float | None, float | None]:
    start = _seconds(entry["start"], f"{where}.start") if "start" in entry else None
    end = _seconds(entry["end"], f"{where}.end") if "end" in entry else None
    if start is not None and end is not None:
        if end == start:
            raise UsageError(f"{where} has zero length (start = end = {start:g} s)")
        if end < start:
            raise UsageError(f"{where} ends ({end:g} s) before it starts ({start:g} s)")
    elif required:
        raise UsageError(f"{where}: needs start and end")
    return start, end


def _segment(entry: Any, where: str, check_text) -> Segment:
    entry = _fields(entry, SEGMENT_KEYS, SEGMENT_KEYS, "a segment", where)
    start, end = _span(entry, where, required=True)
    return Segment(start, end, _text(entry["text"], where, check_text))


def _part(entry: Any, where: str, check_text) -> PartText:
    entry = _fields(entry, PART_KEYS, ("parts", "text"), "a part", where)
    names = entry["parts"]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise UsageError(f"{where}.parts must be a non-empty list of body part names, got {names!r}")
    start, end = _span(entry, where, required=False)
    return PartText(tuple(dict.fromkeys(names)), _text(entry["text"], where, check_text), start, end)
