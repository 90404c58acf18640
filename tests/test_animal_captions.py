"""AnimalML3D's species words and subject substitution on the release's own captions
(../shared/data/animalml3d/motion_captions: 3,710 captions of 38 identities)."""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

import pytest

from helpers import REPO
from omg.errors import UsageError
from omg.text.omgpt import (
    about_animal,
    animal_subjects,
    animal_table,
    animal_words,
    choose_animal,
    find_animal,
    species_of,
    to_animal,
    to_person,
)

ANIMALML3D = REPO.parent / "shared" / "data" / "animalml3d"


def real_captions() -> list[tuple[str, str]]:
    """(identity, caption) of every non-empty caption line of the release."""
    root = ANIMALML3D / "motion_captions"
    if not root.is_dir():
        pytest.skip(f"the real AnimalML3D captions are not at {root} (the shared/ folder beside the checkout)")
    found = []
    for folder in sorted(root.iterdir()):
        for line in (folder / "screenshots.txt").read_text(encoding="utf-8").splitlines():
            if caption := line.split("#")[0].strip():
                found.append((folder.name.split("_")[0], caption))
    return found


def test_every_identity_of_the_release_has_the_species_its_captions_use():
    captions = real_captions()
    identities = {p.name.split("_")[0] for p in (ANIMALML3D / "motion_captions").iterdir()}
    identities |= {p.name for p in (ANIMALML3D / "animals_maa_offsets").iterdir()}
    assert len(identities) == 59 and identities == set(animal_table()[0])
    # derived again from the captions: the animal word of the most subject phrases of each identity
    words = animal_subjects(animal_words())
    used: dict[str, Counter] = {}
    for identity, caption in captions:
        if match := words.search(caption):
            noun = match.group("noun").lower()
            used.setdefault(identity, Counter())[animal_table()[1].get(noun, noun)] += 1
    assert len(used) == 38
    assert {identity: count.most_common(1)[0][0] for identity, count in used.items()} == {
        identity: species_of(identity) for identity in used}
    assert species_of("bearPDD") == "pig" and species_of("canieLTT") == "wolf" and species_of("dog") is None


ARTICLE = re.compile(r"\b(an?)\b", re.IGNORECASE)
DOUBLED = re.compile(r"\b(?:person|cat)\s+(?:a|an|the)\b|\b(?:a|an|the)\s+(?:a|an|the)\s", re.IGNORECASE)


def _count(word: str, text: str) -> int:
    return len(re.findall(rf"\b{word}\b", text, re.IGNORECASE))


def test_subject_substitution_is_well_formed_on_every_real_caption():
    """Animal caption -> "a person" (the human generator's prompt) -> back to the species, and the same
    caption made about a cat (``--animal cat``): exactly one subject replaced, none doubled, none left."""
    captions = real_captions()
    known = sorted(set(animal_table()[0].values()))
    # an animal subject phrase left behind (not a verb such as "ducks", nor "a dog-paddle")
    words = "|".join(re.escape(w).replace(r"\ ", r"\s+") for w in sorted(animal_words(known), key=len, reverse=True))
    animal = re.compile(rf"\b(?:a|an|the)\s+(?:[a-z]+ing\s+)?(?:{words})(?:e?s)?\b(?!-)", re.IGNORECASE)
    failures = []
    for identity, caption in captions:
        species = species_of(identity)
        person = to_person(caption, known)
        back = to_animal(person, species)
        cat = about_animal(caption, "cat", known)
        problems = [
            _count("person", person) != 1 and "not one person",
            bool(animal.search(person)) and "an animal left in the person caption",
            bool(re.search(r"\bits(elf)?\b", person, re.IGNORECASE)) and "its/itself left for a person",
            _count("person", back) != 0 and "a person left in the caption made back",
            _count(species, back) != 1 and f"not one {species} made back",
            bool(re.search(r"\b(their|themselves)\b", back, re.IGNORECASE)) and "their/themselves left for an animal",
            _count("cat", cat) != 1 + _count("cat", caption) - (species == "cat") and "not one cat",
            bool(animal.search(re.sub(r"\b(?:a|an|the)\s+cat\b", "", cat, flags=re.I))) and "another animal left",
            bool(DOUBLED.search(person) or DOUBLED.search(cat)) and "a doubled subject",
        ]
        if problems := [p for p in problems if p]:
            failures.append(f"{identity}: {caption!r} -> {person!r} / {back!r} / {cat!r}: {', '.join(problems)}")
        # the release's usual "a <species> ..." captions come back exactly (the article made right: "A elk",
        # a fox's or lioness's "his"/"her" made "its")
        if re.match(rf"an? {species}\b", caption, re.IGNORECASE):
            expected = ARTICLE.sub("a", re.sub(r"\b(his|her)\b", "its", caption))
            assert ARTICLE.sub("a", back) == expected, (caption, person, back)
    assert len(captions) == 3710 and not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:20])


def test_the_animal_a_prompt_generates_one_rule():
    known = ["cat", "dog", "bear"]
    assert choose_animal("a dog jumps over a log", known) == "dog"
    assert choose_animal("a dog jumps over a log", known, animal="cat") == "cat"  # --animal wins
    assert choose_animal("a grizz walks backwards", known) == "bear"  # the captions' other word for a bear
    with pytest.raises(UsageError, match="names no animal this checkpoint knows; pass --animal"):
        choose_animal("a unicorn jumps", known)
    with pytest.raises(UsageError, match="unknown animal 'unicorn'; this checkpoint knows: cat, dog, bear"):
        choose_animal("a dog jumps", known, animal="unicorn")
    # the prompt is then made about the chosen animal, and about a person for the human generator
    assert about_animal("A dog jumps over a log and wags its tail", "cat", known) == ("A cat jumps over a log and "
                                                                                      "wags its tail")
    assert about_animal("a person kicks with his left leg", "cat", known) == "a cat kicks with its left leg"
    assert about_animal("the cat sits", "cat", known) == "the cat sits"
    assert to_person("a dog jumps over a log", ["cat"]) == "a person jumps over a log"  # any species omg knows
    assert find_animal("a milk cow leaps", ["milk cow"]) == "milk cow"
    # milkcow10L is the "milk cow" its captions say, in substitution and prompts: never the non-word "milkcow"
    assert species_of("milkcow10L") == "milk cow"
    assert to_animal("a person walks and then he stops", "milk cow") == "a milk cow walks and then it stops"
    assert about_animal("a dog leaps over a fence", "milk cow") == "a milk cow leaps over a fence"
    assert to_person("A milk cow lies down", ["milk cow"]) == "A person lies down"


def test_later_mentions_follow_the_new_subject():
    assert to_animal("a man walks forward, then the man sits down and rubs their knee.", "dog") == (
        "a dog walks forward, then the dog sits down and rubs its knee.")
    assert to_animal("a man hands a ball to a woman", "dog") == "a dog hands a ball to a woman"
    assert to_person("A bear stands up. The bear then drops", ["bear"]) == "A person stands up. The person then drops"


def test_animal_words_cover_the_species_files():
    words = animal_words(["red_fox"])
    assert {"dog", "bear", "grizz", "milk cow", "red fox", "hippopotamus"} <= set(words)
    assert Path(REPO / "omg/text/animals.yaml").is_file()
