"""Caption wording: subjects, predicates and modifiers, and how 2-3 captions are drawn from them.

An action decides *what* happened (direction, speed, count, ...) and asks a function here for
the words; ``sample_captions`` then combines them with the clip's random generator. Keep the
order of options stable: captions are drawn by index, and the committed mini shards hold them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NO_WORDS = ("",)
FROM_STANDSTILL = ("from a standstill", "after standing still")
PEOPLE = ("a person", "someone", "a man", "a woman", "the person", "a human")
SPEED_WORDS = {
    "slow": ("slowly", "at a slow pace", ""), "normal": ("",), "fast": ("quickly", "briskly", "at a fast pace"),
}  # fmt: skip
RUN_SPEED_WORDS = {"slow": ("at an easy pace", "lightly", ""), "normal": ("",), "fast": ("at full speed", "very fast")}
STYLE_WORDS = {
    "neutral": ("",),
    "happy": ("happily", "with a bounce in their step", "cheerfully"),
    "tired": ("wearily", "as if exhausted", "with slumped shoulders"),
    "sneaky": ("sneakily", "crouched low", "stealthily"),
    "proud": ("proudly", "with a confident stride", "with the chest held high"),
    "striding": ("with long strides", "taking big steps", "with big strides"),
}
GALLOP_SPEED_WORDS = ("", "at full speed", "quickly")
BOUNDING_SPECIES = ("dog", "cat", "fox")  # their gallop also reads as bounding or dashing


@dataclass(frozen=True)
class CaptionParts:
    """The words of one clip's captions, short of the subject."""

    predicates: tuple[str, ...]  # what the subject does, one is picked per caption
    modifier_groups: tuple[tuple[str, ...], ...] = ()  # one word or phrase is picked from each ("" = none)
    suffixes: tuple[str, ...] = NO_WORDS  # a closing clause, e.g. "and then stops"


def sample_captions(rng: np.random.Generator, subjects: tuple[str, ...], parts: CaptionParts) -> list[str]:
    """2-3 distinct captions: subject, predicate, up to two modifiers (one per group) and a suffix."""

    def pick(options):
        return options[rng.integers(len(options))]

    count, captions = int(rng.integers(2, 4)), []
    for _ in range(20):  # a few tries: small vocabularies can repeat themselves
        modifiers = [m for m in (pick(group) for group in parts.modifier_groups) if m]
        modifiers = [modifiers[i] for i in rng.permutation(len(modifiers))[:2]]  # more than two reads like a list
        words = (pick(subjects), pick(parts.predicates), *modifiers, pick(parts.suffixes))
        text = " ".join(w for w in words if w) + "."
        if text not in captions:
            captions.append(text)
        if len(captions) == count:
            break
    return captions


# ----------------------------------------------------------------------------- people


def human_locomotion(*, run: bool, direction: str, side: str, speed: str, style: str, started: bool, stops: bool):
    verb = ("jogs" if speed == "slow" else "runs") if run else "walks"
    rotation = "counterclockwise" if side == "left" else "clockwise"
    predicates = {
        "forward": ("runs forward", "runs straight ahead", "is running forward") if run else (
            "walks forward", "walks straight ahead", "strolls forward", "is walking forward"),
        "backward": ("walks backwards", "walks backward", "steps backwards", "moves backward"),
        "left": ("walks sideways to the left", "side-steps to the left", "shuffles to the left"),
        "right": ("walks sideways to the right", "side-steps to the right", "shuffles to the right"),
        "circle": (f"{verb} in a circle", f"{verb} in a circle to the {side}", f"{verb} around in a {rotation} circle"),
    }[direction]  # fmt: skip
    if run and speed != "normal" and direction == "forward":
        predicates += ("jogs forward", "jogs ahead") if speed == "slow" else ("sprints forward", "dashes ahead")
    groups = (RUN_SPEED_WORDS[speed] if run else SPEED_WORDS[speed], STYLE_WORDS[style])
    if started:
        groups += (FROM_STANDSTILL,)
    suffixes = ("and then stops", "before coming to a stop") if stops else NO_WORDS
    return CaptionParts(predicates, groups, suffixes)


def human_jump(*, forward: bool, count: int):
    predicates = ("jumps forward", "leaps forward", "does a long jump forward") if forward else (
        "jumps in place", "jumps up and down", "hops on the spot")  # fmt: skip
    return CaptionParts(predicates, ({1: ("",), 2: ("twice",), 3: ("three times",)}[count],))


def human_turn(*, side: str, turns_around: bool):
    predicates = (f"turns to the {side}", f"turns {side}", f"turns around to the {side}")
    if turns_around:
        predicates = (f"turns around to the {side}", "turns around", "turns to face the other way")
    return CaptionParts(predicates, (("", "in place", "on the spot"),))


def human_wave(*, hand: str):
    hands = "both hands" if hand == "both" else f"the {hand} hand"
    predicates = (f"waves with {hands}", f"waves hello with {hands}", f"raises {hands} and waves")
    return CaptionParts(predicates, (("", "while standing still"),))


def human_kick(*, leg: str, high: bool, count: int):
    predicates = (f"kicks with the {leg} leg", f"kicks forward with the {leg} foot",
                  f"does a {'high' if high else 'low'} kick with the {leg} leg")  # fmt: skip
    return CaptionParts(predicates, (("",) if count == 1 else ("twice",),))


def human_sit(*, stands_up: bool, slow: bool):
    suffixes = ("and then stands back up", "and gets up again") if stands_up else NO_WORDS
    return CaptionParts(("sits down", "takes a seat", "sits down on a chair"), (_slowly(slow),), suffixes)


def human_crouch(*, stands_up: bool, slow: bool):
    suffixes = ("and stands back up", "and then rises again") if stands_up else NO_WORDS
    return CaptionParts(("crouches down", "squats down", "bends the knees and squats"), (_slowly(slow),), suffixes)


def human_punch(*, count: int):
    predicates = ("punches", "throws punches", "boxes", f"throws {count} punches", "punches the air")
    return CaptionParts(predicates, (("", "with both fists", "alternating fists"),))


def human_idle(*, looks_around: bool, style: str):
    predicates = ("stands and looks around", "looks around while standing") if looks_around else (
        "stands still", "stands in place", "waits idly")  # fmt: skip
    return CaptionParts(predicates, (STYLE_WORDS[style],))


def _slowly(slow: bool) -> tuple[str, ...]:
    return ("", "slowly") if slow else NO_WORDS


# ----------------------------------------------------------------------------- animals


def animal_subjects(category: str, size: float) -> tuple[str, ...]:
    """"a dog", "the dog", and "a big dog" / "a small dog" when this individual is notably sized."""
    adjective = "big " if size > 1.06 else "small " if size < 0.94 else ""
    return (f"a {category}", f"the {category}", f"a {adjective}{category}")


def animal_travel(*, action: str, category: str, pace: str, side: str | None, started: bool):
    """Walk, trot, gallop or a walking turn to ``side``."""
    predicates = {
        "walk": ("walks forward", "walks ahead", "is walking forward", "strolls along"),
        "trot": ("trots forward", "trots along", "is trotting ahead", "moves forward at a trot"),
        "gallop": ("gallops forward", "runs forward at a gallop", "is galloping ahead", "runs fast"),
        "turn": (f"turns {side} while walking", f"walks in a curve to the {side}", f"walks and turns {side}"),
    }[action]  # fmt: skip
    if action == "gallop" and category in BOUNDING_SPECIES:
        predicates += ("bounds forward", "dashes forward", "sprints ahead")
    groups = (SPEED_WORDS[pace] if action != "gallop" else GALLOP_SPEED_WORDS,)
    if started:
        groups += (FROM_STANDSTILL,)
    return CaptionParts(predicates, groups)


def animal_jump():
    return CaptionParts(("jumps forward", "leaps forward", "makes a big leap forward", "jumps over an obstacle"))


def animal_sit(*, slow: bool):
    predicates = ("sits down", "sits down on its haunches", "lowers itself into a sitting position", "sits")
    return CaptionParts(predicates, (_slowly(slow),))


def animal_lie(*, slow: bool):
    predicates = ("lies down", "lies down on the ground", "lies down to rest", "gets down onto the ground")
    return CaptionParts(predicates, (_slowly(slow),))


def animal_idle(*, looks_around: bool, wags: bool):
    predicates = ("stands and looks around", "looks around") if looks_around else (
        "stands still", "stands in place", "stands idle")  # fmt: skip
    return CaptionParts(predicates, (("while wagging its tail", "wagging its tail") if wags else NO_WORDS,))
