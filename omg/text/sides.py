"""Captions seen in a mirror: left <-> right, clockwise <-> counterclockwise.

A motion mirrored across the body's sagittal plane (``Representation.mirror``) does with its
right what the original did with its left and turns the other way; its caption says so when
every side word is swapped: whole words only ("bright", "leftover" stay), the case of each word
kept ("Left" -> "Right", "LEFT" -> "RIGHT"), hyphenated forms included ("left-handed",
"counter-clockwise"). "right" that means "correct" or "just" is left alone in the idioms
``RIGHT_IDIOMS`` ("all right", "right away", "right now", "right after", ...), unless the word
before it makes it a side (``SIDE_CONTEXT``: "turns right after ...", "his right then ...").
"""

from __future__ import annotations

import re

# every side word and its mirror image (lower case); the longest alternatives are tried first
SIDE_WORDS = {
    "left": "right", "right": "left",
    "leftward": "rightward", "rightward": "leftward", "leftwards": "rightwards", "rightwards": "leftwards",
    "leftmost": "rightmost", "rightmost": "leftmost",
    "lefthand": "righthand", "righthand": "lefthand",
    "clockwise": "counterclockwise", "counterclockwise": "clockwise", "counter-clockwise": "clockwise",
    "anticlockwise": "clockwise", "anti-clockwise": "clockwise",
}  # fmt: skip
RIGHT_IDIOMS = ("all right", "alright", "right away", "right now", "right after", "right before", "right then",
                "right there", "right here", "right on", "right at the end", "right at the start")

# a word before "right" that makes it a side even where an idiom follows ("turns right after")
SIDE_CONTEXT = re.compile(r"(?:the|his|her|their|its|to|both|(?:turn|step|lean|look|move|walk|run|jog|jump|hop|spin|"
                          r"pivot|rotate|veer|shift|swing|kick|punch|wave|raise|lift|go)(?:s|es|ed|ing)?|went)\s+$",
                          re.IGNORECASE)
_WORDS = re.compile(r"(?<!\w)(" + "|".join(sorted(map(re.escape, SIDE_WORDS), key=len, reverse=True))
                    + r")(?![\w])", re.IGNORECASE)
_IDIOMS = re.compile(r"\b(?:" + "|".join(re.escape(i).replace(r"\ ", r"\s+") for i in RIGHT_IDIOMS) + r")\b",
                     re.IGNORECASE)


def _same_case(original: str, word: str) -> str:
    if original.isupper() and len(original) > 1:
        return word.upper()
    return word[:1].upper() + word[1:] if original[:1].isupper() else word


def _is_side(text: str, m: re.Match, idioms: list[tuple[int, int]]) -> bool:
    idiom = any(a <= m.start() < b for a, b in idioms)
    return not idiom or bool(SIDE_CONTEXT.search(text[: m.start()]))


def mirror_caption(text: str) -> str:
    """``text`` with every side word swapped for its mirror image (module docstring); applied twice
    it gives the text back, except that anticlockwise / anti-clockwise come back as
    counterclockwise."""
    idioms = [m.span() for m in _IDIOMS.finditer(text)]

    def swap(m: re.Match) -> str:
        if not _is_side(text, m, idioms):
            return m.group(0)
        return _same_case(m.group(0), SIDE_WORDS[m.group(0).lower()])

    return _WORDS.sub(swap, text)


# the words on the left-hand side of the mirror (sign +1); their images (SIDE_WORDS) have sign -1. A
# counterclockwise turn, seen from above, is a turn to the left.
LEFT_WORDS = frozenset({"left", "leftward", "leftwards", "leftmost", "lefthand", "counterclockwise",
                        "counter-clockwise", "anticlockwise", "anti-clockwise"})


def side_spans(text: str) -> list[tuple[int, int, int]]:
    """The side words of ``text`` that ``mirror_caption`` would swap: (start, end, sign) character
    spans, sign +1 for a left word (left, leftward, counterclockwise, ...) and -1 for a right one."""
    idioms = [m.span() for m in _IDIOMS.finditer(text)]
    return [(m.start(), m.end(), 1 if m.group(0).lower() in LEFT_WORDS else -1)
            for m in _WORDS.finditer(text) if _is_side(text, m, idioms)]


def names_a_side(text: str) -> bool:
    """Whether ``text`` names a side or a turning sense that mirroring would change."""
    return mirror_caption(text) != text


def _cosine_distance(a, b):
    """(N, D), (M, D) -> (N, M): 1 - cosine similarity."""
    import torch.nn.functional as F

    return 1 - F.normalize(a, dim=-1) @ F.normalize(b, dim=-1).T


def token_sides(text: str, spans: list[tuple[int, int]]) -> list[int]:
    """Per token of ``text`` given by its (start, end) characters ((0, 0) for a special token), the
    sign of the side word it is part of (``side_spans``: +1 left, -1 right), 0 for any other token."""
    sides = side_spans(text)
    return [next((sign for start, end, sign in sides if a < end and start < b), 0) if b > a else 0
            for a, b in spans]


def side_tokens(encoder, text: str) -> list[int] | None:
    """The positions, in ``encoder``'s token features of ``text``, of the tokens of its side words
    (``token_sides``); None where the encoder does not say which characters each token covers."""
    spans = encoder.token_spans(text)
    if spans is None:
        return None
    return [i for i, sign in enumerate(token_sides(text, spans)) if sign]


FEATURES = ("sentence", "token mean", "tokens", "side word")


def side_separation(encoder, captions: list[tuple[str, str]]) -> dict[str, dict[str, float]]:
    """How far apart a text encoder puts a caption and its mirror image (left <-> right), relative
    to captions of other actions and to other captions of the same action: does sidedness survive
    in the text features a generator reads?

    ``captions``: (caption, action label) pairs; every caption that names a side is compared with
    its ``mirror_caption``. Distances are cosine distances (1 - cos), per feature (``FEATURES``):

    - ``sentence``: the EOT feature (``TextFeatures.eot_embedding``), the sentence summary the
      ControlNet's AdaIN and expert gates read (MiniLM's is its mean-pooled sentence embedding);
    - ``token mean``: the mean of the other token features;
    - ``tokens``: the symmetric Chamfer distance between the two captions' sets of tokens (each
      token's nearest token in the other caption, averaged both ways): what a cross-attention over
      the tokens could tell apart;
    - ``side word``: from the sided caption's side-word tokens (``side_tokens``) to the other
      caption, the largest over those tokens of the distance to the nearest token there: how far
      the word that names the side is from anything in the other caption (left out for an encoder
      without ``token_spans``).

    Two captions are of another action when neither their labels nor a label and the other's mirror
    image (``mirror_caption``: walk-left / walk-right) are equal, so a side swap is never counted
    as a change of action.

    Returns per feature: ``side`` (mean distance caption <-> mirror), ``action`` (mean distance
    between captions of other actions), ``ratio`` (side / action: left/right pairs are ``ratio`` as
    far apart as different actions), ``rank`` (per sided caption, the fraction of the captions of
    other actions that lie nearer to it than its mirror image, averaged: 0 when a side swap is the
    smallest change there is, 0.5 when it counts as much as a typical change of action),
    ``same_action`` (mean distance to the other captions of the same action: other styles,
    paraphrases; nan when there are none), ``same_ratio`` (side / same_action; nan where that is 0,
    as for the side word of captions that differ only elsewhere) and ``captions`` (how many name a
    side).
    """
    import torch

    texts = list(dict.fromkeys(text for text, _ in captions))
    action = dict(captions)
    sided = [t for t in texts if names_a_side(t)]
    if not sided:
        raise ValueError("no caption names a side (left, right, clockwise, ...)")
    mirrors = [mirror_caption(t) for t in sided]
    everything = texts + mirrors
    with torch.no_grad():
        features = encoder(everything)
    n = len(everything)
    tokens = [features.tokens[b, features.mask[b].bool()].double() for b in range(n)]
    sentence = features.eot_embedding().double()
    mean = torch.stack([x[:-1].mean(0) if len(x) > 1 else x[0] for x in tokens])
    sides = {t: side_tokens(encoder, t) for t in sided}
    names = [f for f in FEATURES if f != "side word" or all(s for s in sides.values())]

    def chamfer(a, b) -> float:
        d = _cosine_distance(a, b)
        return float((d.min(1).values.mean() + d.min(0).values.mean()) / 2)

    def dist(name: str, i: int, j: int, words: list[int]) -> float:
        if name == "sentence":
            return float(_cosine_distance(sentence[i:i + 1], sentence[j:j + 1]))
        if name == "token mean":
            return float(_cosine_distance(mean[i:i + 1], mean[j:j + 1]))
        if name == "tokens":
            return chamfer(tokens[i], tokens[j])
        return float(_cosine_distance(tokens[i][words], tokens[j]).min(1).values.max())

    out = {}
    for name in names:
        side, action_d, rank, same = [], [], [], []
        for k, text in enumerate(sided):
            i, words = texts.index(text), sides[text]
            mirrored = mirror_caption(action[text])
            others = [dist(name, i, j, words) for j, other in enumerate(texts)
                      if action[other] not in (action[text], mirrored)]
            same += [dist(name, i, j, words) for j, other in enumerate(texts)
                     if action[other] == action[text] and other != text]
            side.append(dist(name, i, len(texts) + k, words))
            if others:
                rank.append(sum(d < side[-1] for d in others) / len(others))
            action_d.extend(others)
        if not action_d:
            raise ValueError("every caption has the same action or its mirror image: nothing to compare a side "
                             "swap with")
        mean_side, mean_action = sum(side) / len(side), sum(action_d) / len(action_d)
        mean_same = sum(same) / len(same) if same else float("nan")
        same_ratio = mean_side / mean_same if same and mean_same > 1e-9 else float("nan")
        out[name] = {"side": mean_side, "action": mean_action, "ratio": mean_side / mean_action,
                     "same_action": mean_same, "same_ratio": same_ratio,
                     "rank": sum(rank) / len(rank), "captions": len(sided)}
    return out
