"""Who a caption is about: OmniMotionGPT's subject substitution.

OmniMotionGPT aligns human and animal motion through text: a human caption with its subject
replaced by an animal's name ("a person jumps" -> "a dog jumps", C̃^a in the paper) describes the
animal motion the human motion should become, and an animal caption with its subject replaced by
"a person" asks omg's human generator for the human motion to start from. The rule:

- the first human subject phrase (``a person``, ``the man``, ``someone``, ``she`` ...) becomes
  the new subject, keeping a capital first letter; when the caption names none, the subject
  is put in front of it ("jumps twice" -> "a dog jumps twice");
- later pronouns follow the new subject: he/she/him -> it, his/her(s) -> its, himself/herself
  -> itself for an animal; its -> their, itself -> themselves for "a person";
- for the reverse direction, ``animal_subjects(names)`` gives the phrases of known animals.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

# Subject phrases of HumanML3D-style captions, longest first so "the person" wins over "person".
HUMAN_NOUNS = ("person", "man", "woman", "human", "guy", "girl", "boy", "lady", "gentleman", "individual", "figure",
               "character", "subject", "people", "adult", "child", "kid", "player", "dancer", "actor", "walker")
DETERMINERS = ("a", "an", "the", "this", "that", "one")
ADJECTIVES = ("young", "old", "tall", "short", "little", "small", "big", "elderly")
HUMAN_PRONOUN_SUBJECTS = ("someone", "somebody", "he", "she")

_NON_HUMAN_PRONOUNS = {"he": "it", "she": "it", "him": "it", "his": "its", "her": "its", "hers": "its",
                       "himself": "itself", "herself": "itself"}
_HUMAN_PRONOUNS = {"its": "their", "itself": "themselves"}  # "it" may be an object: left as it is


def article(name: str) -> str:
    """``"a dog"``, ``"an elephant"``: the indefinite subject phrase of a category name; a phrase
    that already starts with a determiner is returned as it is."""
    name = " ".join(name.strip().replace("_", " ").split())
    if not name:
        raise ValueError("an empty name has no subject phrase")
    if name.split()[0].lower() in DETERMINERS:
        return name
    return f"{'an' if name[0].lower() in 'aeiou' else 'a'} {name}"


def _phrase_pattern(nouns: Iterable[str], bare: Iterable[str] = ()) -> re.Pattern:
    nouns = sorted({n.lower() for n in nouns}, key=len, reverse=True)
    noun = "|".join(re.escape(n) for n in nouns)
    det = "|".join(DETERMINERS)
    adj = "|".join(ADJECTIVES)
    alternatives = [rf"(?:(?:{det})\s+)?(?:(?:{adj})\s+)*(?:{noun})(?:s)?"]
    if bare := sorted(set(bare), key=len, reverse=True):
        alternatives.append("|".join(re.escape(b) for b in bare))
    return re.compile(rf"\b(?:{'|'.join(alternatives)})\b", re.IGNORECASE)


HUMAN_SUBJECT = _phrase_pattern(HUMAN_NOUNS, HUMAN_PRONOUN_SUBJECTS)


def animal_subjects(names: Sequence[str]) -> re.Pattern:
    """The pattern of animal subject phrases (``a dog``, ``the big horse``, ``cats``) for ``names``."""
    if not names:
        raise ValueError("no animal names given")
    return _phrase_pattern([n.replace("_", " ") for n in names])


def _capitalized_like(original: str, replacement: str) -> str:
    return replacement[:1].upper() + replacement[1:] if original[:1].isupper() else replacement


def _swap_pronouns(text: str, table: dict[str, str]) -> str:
    pattern = re.compile(rf"\b({'|'.join(table)})\b", re.IGNORECASE)
    return pattern.sub(lambda m: _capitalized_like(m.group(0), table[m.group(0).lower()]), text)


def substitute_subject(caption: str, subject: str, pattern: re.Pattern = HUMAN_SUBJECT) -> str:
    """``caption`` with its first subject phrase (``pattern``: human subjects by default) replaced by
    ``subject`` (a phrase such as "a dog"; a bare name gets its article), and the pronouns that
    referred to it made to fit: ``substitute_subject("The man turns and he waves his arm", "horse")``
    is "A horse turns and it waves its arm". A caption without a subject phrase gets ``subject`` in front.
    """
    caption = " ".join(caption.split())
    subject = article(subject)
    to_human = bool(HUMAN_SUBJECT.fullmatch(subject))
    match = pattern.search(caption)
    if match is None:
        body = caption[:1].lower() + caption[1:] if caption else caption
        new = f"{subject} {body}".strip()
        return _capitalized_like(caption, new) if caption else new
    head, tail = caption[: match.start()], caption[match.end():]
    replaced = _capitalized_like(match.group(0), subject) if match.start() == 0 else subject
    if to_human:
        tail = _swap_pronouns(tail, _HUMAN_PRONOUNS) if pattern is not HUMAN_SUBJECT else tail
    else:
        tail = _swap_pronouns(tail, _NON_HUMAN_PRONOUNS)
    return f"{head}{replaced}{tail}"


def to_animal(caption: str, animal: str) -> str:
    """A human caption made about ``animal`` (OmniMotionGPT's C̃^a)."""
    return substitute_subject(caption, animal, HUMAN_SUBJECT)


def to_person(caption: str, animals: Sequence[str]) -> str:
    """An animal caption made about "a person" (the prompt of the human generator); ``animals``: the
    known animal names, e.g. a checkpoint's categories."""
    return substitute_subject(caption, "a person", animal_subjects(animals))


def find_animal(caption: str, animals: Sequence[str]) -> str | None:
    """The first of ``animals`` that ``caption`` names (as a word, singular or plural), or None."""
    best: tuple[int, str] | None = None
    for name in animals:
        m = re.search(rf"\b{re.escape(name.replace('_', ' '))}(?:s|es)?\b", caption, re.IGNORECASE)
        if m and (best is None or m.start() < best[0]):
            best = (m.start(), name)
    return None if best is None else best[1]


LEG_WORDS = frozenset({"leg", "legs", "foot", "feet", "knee", "knees", "kick", "kicks", "kicking", "kicked",
                       "stomp", "stomps", "stomping", "hop", "hops", "hopping"})
ARM_WORDS = frozenset({"arm", "arms", "hand", "hands", "wrist", "elbow", "wave", "waves", "waving", "waved", "punch",
                       "punches", "punching", "throw", "throws", "throwing", "swing", "swings", "reach", "reaches"})


def one_sided_limb(caption: str) -> tuple[str, str] | None:
    """("leg" | "arm", "left" | "right") when a caption names one side and one kind of limb ("a person
    kicks with the left leg" -> ("leg", "left")), else None (both sides, no side, or legs and arms)."""
    words = re.findall(r"[a-z]+", caption.lower())
    sides = {w for w in words if w in ("left", "right")}
    limbs = {"leg" if w in LEG_WORDS else "arm" for w in words if w in LEG_WORDS or w in ARM_WORDS}
    if len(sides) != 1 or len(limbs) != 1 or "both" in words:
        return None
    return limbs.pop(), sides.pop()
