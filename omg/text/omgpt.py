"""Who a caption is about: OmniMotionGPT's subject substitution, and which animal a prompt asks for.

OmniMotionGPT aligns human and animal motion through text: a human caption with its subject
replaced by an animal's name ("a person jumps" -> "a dog jumps", C̃^a in the paper) describes the
animal motion the human motion should become, and an animal caption with its subject replaced by
"a person" asks omg's human generator for the human motion to start from. The rule:

- the first subject phrase (``a person``, ``the man``, ``someone``, ``she``; for animals ``a bear``,
  ``the grazing deer``, ``a milk cow``) becomes the new subject, keeping a capital first letter;
  when the caption names none, the subject is put in front of it ("jumps twice" -> "a dog jumps
  twice");
- later mentions of the same subject follow it: ``the man`` -> ``the dog``; pronouns he/she/him
  -> it, his/her(s)/their(s) -> its, himself/herself/themselves -> itself for an animal; its ->
  their, itself -> themselves for "a person" ("it" may be an object and is left as it is);
- the animal words known to captions are those of ``animals.yaml`` (AnimalML3D's identities ->
  species, and the other words their captions use), of ``species.yaml`` and the names given.

``choose_animal`` is the one rule of which animal a prompt generates (``omg generate --animal``
and ``OmniMotionModule.sample``): the explicit animal, else the one the prompt names.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Iterable, Sequence
from importlib import resources

import yaml

from omg.errors import UsageError

ANIMALS_FILE = "animals.yaml"

# Subject phrases of HumanML3D-style captions, longest first so "the person" wins over "person".
HUMAN_NOUNS = ("person", "man", "woman", "human", "guy", "girl", "boy", "lady", "gentleman", "individual", "figure",
               "character", "subject", "people", "adult", "child", "kid", "player", "dancer", "actor", "walker")
DETERMINERS = ("a", "an", "the", "this", "that", "one")
ADJECTIVES = ("young", "old", "tall", "short", "little", "small", "big", "elderly")
HUMAN_PRONOUN_SUBJECTS = ("someone", "somebody", "he", "she")

_NON_HUMAN_PRONOUNS = {"he": "it", "she": "it", "him": "it", "his": "its", "her": "its", "hers": "its",
                       "their": "its", "theirs": "its", "himself": "itself", "herself": "itself",
                       "themselves": "itself"}
_HUMAN_PRONOUNS = {"its": "their", "itself": "themselves"}  # "it" may be an object: left as it is


@functools.cache
def animal_table() -> tuple[dict[str, str], dict[str, str]]:
    """({AnimalML3D identity: species word}, {other caption word: species word}) of ``animals.yaml``."""
    data = yaml.safe_load(resources.files("omg.text").joinpath(ANIMALS_FILE).read_text(encoding="utf-8"))
    return dict(data["identities"]), dict(data["aliases"])


def species_of(identity: str) -> str | None:
    """The species word of an AnimalML3D identity ("bear3EP" -> "bear", "canieLTT" -> "wolf"), None when
    the identity is not one of the release's."""
    return animal_table()[0].get(identity)


@functools.cache
def _known_animal_words() -> tuple[str, ...]:
    from omg.text.habit import SpeciesBook

    identities, aliases = animal_table()
    return tuple(sorted({*identities.values(), *aliases, *(n.replace("_", " ") for n in SpeciesBook.load().names)}))


def animal_words(names: Iterable[str] = ()) -> list[str]:
    """Every word a caption may name an animal by: ``names`` and the species and aliases that omg knows."""
    return sorted({*(n.replace("_", " ") for n in names), *_known_animal_words()})


def _words_for(name: str) -> list[str]:
    """The words that name the animal ``name``: itself and its aliases ("bear": bear, grizz)."""
    return [name.replace("_", " "), *(word for word, species in animal_table()[1].items() if species == name)]


def article(name: str) -> str:
    """``"a dog"``, ``"an elephant"``: the indefinite subject phrase of a category name; a phrase
    that already starts with a determiner is returned as it is."""
    name = " ".join(name.strip().replace("_", " ").split())
    if not name:
        raise ValueError("an empty name has no subject phrase")
    if name.split()[0].lower() in DETERMINERS:
        return name
    return f"{'an' if name[0].lower() in 'aeiou' else 'a'} {name}"


def _alternation(words: Iterable[str]) -> str:
    """Words as a regex alternation, longest first, a space matching any run of white space."""
    return "|".join(re.escape(w).replace(r"\ ", r"\s+") for w in sorted(set(words), key=len, reverse=True))


def _phrase_pattern(nouns: Iterable[str], bare: Iterable[str] = ()) -> re.Pattern:
    """Subject phrases of ``nouns``: an optional determiner, then descriptive words (adjectives, and after a
    determiner -ing words: "a grazing deer"), then the noun (group ``noun``), singular or plural; and the
    ``bare`` words (pronouns)."""
    nouns = {n.lower() for n in nouns}
    det, adj = "|".join(DETERMINERS), "|".join(ADJECTIVES)
    lead = rf"(?:(?:{det})\s+(?:(?:{adj}|[a-z]+ing)\s+)*|(?:(?:{adj})\s+)*)"
    alternatives = [rf"{lead}(?P<noun>{_alternation(nouns)})(?:e?s)?"]
    if bare := set(bare):
        alternatives.append(_alternation(bare))
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
    ``subject`` (a phrase such as "a dog"; a bare name gets its article), its later mentions ("the man")
    and the pronouns that referred to it made to fit: ``substitute_subject("The man turns and he waves
    his arm", "horse")`` is "A horse turns and it waves its arm". A caption without a subject phrase gets
    ``subject`` in front.
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
    if match.group("noun"):  # "the man" later in the caption is the same man
        definite = "the " + subject.split(maxsplit=1)[1] if subject.split()[0].lower() in DETERMINERS else subject
        again = re.compile(rf"\bthe\s+{re.escape(match.group('noun'))}\b", re.IGNORECASE)
        tail = again.sub(lambda m: _capitalized_like(m.group(0), definite), tail)
    if to_human:
        tail = _swap_pronouns(tail, _HUMAN_PRONOUNS) if pattern is not HUMAN_SUBJECT else tail
    else:
        tail = _swap_pronouns(tail, _NON_HUMAN_PRONOUNS)
    return f"{head}{replaced}{tail}"


def to_animal(caption: str, animal: str) -> str:
    """A human caption made about ``animal`` (OmniMotionGPT's C̃^a)."""
    return substitute_subject(caption, animal, HUMAN_SUBJECT)


def to_person(caption: str, animals: Sequence[str] = ()) -> str:
    """An animal caption made about "a person" (the prompt of the human generator); ``animals``: animal
    names beyond the species omg knows, e.g. a checkpoint's categories."""
    return substitute_subject(caption, "a person", animal_subjects(animal_words(animals)))


def about_animal(caption: str, animal: str, animals: Sequence[str] = ()) -> str:
    """A prompt made about ``animal``: its first subject, human ("a person") or animal ("a dog", any of
    ``animal_words(animals)``), replaced; a prompt already about ``animal`` is returned as it is."""
    pattern = _phrase_pattern([*HUMAN_NOUNS, *animal_words([*animals, animal])], HUMAN_PRONOUN_SUBJECTS)
    match = pattern.search(" ".join(caption.split()))
    if match and match.group("noun") and match.group("noun").lower() in _words_for(animal):
        return caption
    return substitute_subject(caption, animal, pattern)


def find_animal(caption: str, animals: Sequence[str]) -> str | None:
    """The first of ``animals`` that ``caption`` names (as a word or by an alias, singular or plural), or None."""
    best: tuple[int, str] | None = None
    for name in animals:
        m = re.search(rf"\b(?:{_alternation(_words_for(name))})(?:s|es)?\b", caption, re.IGNORECASE)
        if m and (best is None or m.start() < best[0]):
            best = (m.start(), name)
    return None if best is None else best[1]


def choose_animal(prompt: str, animals: Sequence[str], animal: str | None = None) -> str:
    """Which of ``animals`` (a checkpoint's) a prompt generates: ``animal`` when given (an explicit choice
    wins over the prompt's words, and the prompt is then made about it), else the one the prompt names.
    An unknown ``animal``, or a prompt naming none without one, is a one-line error listing the known."""
    known = ", ".join(animals) or "none (train the model first)"
    if animal is not None:
        if animal not in animals:
            raise UsageError(f"unknown animal {animal!r}; this checkpoint knows: {known}")
        return animal
    if (named := find_animal(prompt, animals)) is None:
        raise UsageError(f"the prompt {prompt!r} names no animal this checkpoint knows; pass --animal (known: {known})")
    return named


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


def caption_key(caption: str) -> str:
    """A caption compared without case, spacing or a final full stop ("A person walks." is "a person walks"):
    how an evaluation recognises a retrieval clip captioned by one of its prompts."""
    return " ".join(caption.lower().split()).rstrip(".")
