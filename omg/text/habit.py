"""Category knowledge: species descriptions, and retrieval of the nearest known category by text.

Behave Your Motion conditions its motion model on a text embedding of each category's habit
description (size, weight, speed, limb length, where force is exerted) and, for a species
never seen in training, uses the habit latent of the known category whose description is
nearest in that embedding space (Euclidean distance). The descriptions live in
``species.yaml`` beside this module (``name: description``); a user YAML in the same format
adds or overrides species, so a new species needs a description, not retraining.
"""

from __future__ import annotations

import difflib
from importlib import resources
from pathlib import Path
from typing import Mapping, Sequence

import torch
import yaml
from torch import Tensor

from omg.errors import UsageError
from omg.files import read_text
from omg.text.base import TextEncoder

BUILTIN = "species.yaml"
MIN_DESCRIPTION_WORDS = 3  # shorter text is taken for a species name, not a description


def species_key(name: str) -> str:
    """The book's spelling of a species name: lower case, words joined by underscores ("Red Fox" -> red_fox)."""
    return "_".join(name.strip().lower().replace("-", " ").replace("_", " ").split())


def read_species_file(path: Path | str) -> dict[str, str]:
    """A YAML file of ``name: description`` -> {species key: description}; bad files are one-line errors."""
    path = Path(path)
    return parse_species(read_text(path, "species file"), str(path))  # a regular UTF-8 file of bounded size


def parse_species(text: str, where: str) -> dict[str, str]:
    """YAML text of ``name: description`` (from ``where``, named in errors) -> {species key: description}."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UsageError(f"species file {where} is not valid YAML: {' '.join(str(e).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise UsageError(f"species file {where} must map species names to descriptions, got a {type(data).__name__}")
    book: dict[str, str] = {}
    for name, description in data.items():
        key = species_key(str(name))
        if not key:
            raise UsageError(f"species file {where}: empty species name")
        if not isinstance(description, str) or not description.strip():
            raise UsageError(f"species file {where}: {name!r} needs a non-empty description (a string)")
        if key in book:
            raise UsageError(f"species file {where}: {name!r} is given twice")
        book[key] = " ".join(description.split())
    return book


class SpeciesBook:
    """Species name -> habit description: the package's ``species.yaml``, plus a user's file."""

    def __init__(self, descriptions: Mapping[str, str]):
        self._descriptions = {species_key(name): " ".join(text.split()) for name, text in descriptions.items()}

    @classmethod
    def load(cls, extra: str | Path | None = None) -> SpeciesBook:
        """The built-in species, with those of ``extra`` (a YAML of ``name: description``) added or overriding."""
        text = resources.files("omg.text").joinpath(BUILTIN).read_text(encoding="utf-8")
        book = parse_species(text, f"omg/text/{BUILTIN}")
        if extra is not None:
            book.update(read_species_file(extra))
        return cls(book)

    @property
    def names(self) -> list[str]:
        return sorted(self._descriptions)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and species_key(name) in self._descriptions

    def __len__(self) -> int:
        return len(self._descriptions)

    def description(self, name: str) -> str:
        """The description of a known species; an unknown name is an error listing the known ones."""
        key = species_key(name)
        if key in self._descriptions:
            return self._descriptions[key]
        raise UsageError(self._unknown(name))

    def descriptions(self, names: Sequence[str] | None = None) -> dict[str, str]:
        """{name: description} of ``names`` (every species when None), e.g. a model's known categories."""
        return {name: self.description(name) for name in (self.names if names is None else names)}

    def describe(self, query: str) -> str:
        """A known species name -> its description; any other text of >= 3 words is the description itself."""
        if not query or not query.strip():
            raise UsageError("empty species: give a known species name or a description of the animal")
        if query in self:
            return self.description(query)
        if len(query.split()) >= MIN_DESCRIPTION_WORDS:
            return " ".join(query.split())
        raise UsageError(self._unknown(query, f"; or describe the animal in {MIN_DESCRIPTION_WORDS} words or more"))

    def _unknown(self, name: str, alternative: str = "") -> str:
        close = difflib.get_close_matches(species_key(name), self.names, n=3, cutoff=0.6)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        return f"unknown species {name!r}{hint}{alternative}; known species: {', '.join(self.names)}"


def sentence_embeddings(encoder: TextEncoder, texts: Sequence[str]) -> Tensor:
    """(N, E) float32 on the encoder's device: each text's sentence embedding (the EOT feature)."""
    if isinstance(texts, str):
        raise TypeError(f"sentence_embeddings takes a list of texts, got the single string {texts!r}")
    return encoder(list(texts)).eot_embedding().float()


def category_distances(encoder: TextEncoder, query_description: str, known: Mapping[str, str]) -> dict[str, float]:
    """Euclidean distance from the query to each known category's description, in the sentence-embedding
    space with embeddings scaled to unit length: the sentence embedding as both model cards define it
    (bge-base-en-v1.5 and all-MiniLM-L6-v2 end in a normalisation), so encoders that keep their
    sentence feature on the token scale (MiniLM's mean) are compared on the same footing."""
    if not known:
        raise UsageError("no known categories to retrieve from")
    if not query_description or not query_description.strip():
        raise UsageError("empty species description")
    names = list(known)
    embeddings = sentence_embeddings(encoder, [query_description, *(known[name] for name in names)])  # (1 + K, E)
    embeddings = torch.nn.functional.normalize(embeddings, dim=-1)
    distances = torch.linalg.vector_norm(embeddings[1:] - embeddings[:1], dim=-1)  # (K,)
    return {name: float(d) for name, d in zip(names, distances.cpu())}


def nearest_category(encoder: TextEncoder, query_description: str, known: Mapping[str, str]) -> tuple[str, float]:
    """The known category whose description is nearest the query (Euclidean: the paper's retrieval), and the
    distance."""
    distances = category_distances(encoder, query_description, known)
    name = min(distances, key=distances.__getitem__)
    return name, distances[name]
