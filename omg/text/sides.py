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


def mirror_caption(text: str) -> str:
    """``text`` with every side word swapped for its mirror image (module docstring); applied twice
    it gives the text back, except that anticlockwise / anti-clockwise come back as
    counterclockwise."""
    idioms = [m.span() for m in _IDIOMS.finditer(text)]

    def swap(m: re.Match) -> str:
        idiom = any(a <= m.start() < b for a, b in idioms)
        if idiom and not SIDE_CONTEXT.search(text[: m.start()]):
            return m.group(0)
        return _same_case(m.group(0), SIDE_WORDS[m.group(0).lower()])

    return _WORDS.sub(swap, text)


def names_a_side(text: str) -> bool:
    """Whether ``text`` names a side or a turning sense that mirroring would change."""
    return mirror_caption(text) != text


def _cosine_distance(a, b):
    """(N, D), (M, D) -> (N, M): 1 - cosine similarity."""
    import torch.nn.functional as F

    return 1 - F.normalize(a, dim=-1) @ F.normalize(b, dim=-1).T


def side_separation(encoder, captions: list[tuple[str, str]]) -> dict[str, dict[str, float]]:
    """How far apart a text encoder puts a caption and its mirror image (left <-> right), relative
    to captions of other actions: does sidedness survive in the text features a generator reads?

    ``captions``: (caption, action label) pairs; every caption that names a side is compared with
    its ``mirror_caption``. Distances are cosine distances (1 - cos) between

    - ``sentence``: the sentence features (``TextFeatures.eot_embedding``), and
    - ``tokens``: the token features, as the symmetric Chamfer distance between the two captions'
      sets of tokens (each token's nearest token in the other caption, averaged both ways): what a
      cross-attention over the tokens could tell apart.

    Returns per feature: ``side`` (mean distance caption <-> mirror), ``action`` (mean distance
    between captions of different actions), ``ratio`` (side / action) and ``rank`` (per sided
    caption, the fraction of the captions of other actions that lie nearer to it than its mirror
    image, averaged: 0 when a side swap is the smallest change there is, 0.5 when it counts as
    much as a typical change of action), ``same_action`` (mean distance to the other captions of
    the same action: the other styles and wordings) and ``captions`` (how many name a side).
    """
    import torch

    texts = list(dict.fromkeys(text for text, _ in captions))
    action = dict(captions)
    sided = [t for t in texts if names_a_side(t)]
    if not sided:
        raise ValueError("no caption names a side (left, right, clockwise, ...)")
    mirrors = [mirror_caption(t) for t in sided]
    with torch.no_grad():
        features = encoder(texts + mirrors)
    tokens = [features.tokens[b, features.mask[b].bool()].double() for b in range(len(texts) + len(mirrors))]
    sentence = features.eot_embedding().double()

    def chamfer(a, b) -> float:
        d = _cosine_distance(a, b)
        return float((d.min(1).values.mean() + d.min(0).values.mean()) / 2)

    out = {}
    for name in ("sentence", "tokens"):
        def dist(i: int, j: int) -> float:
            return float(_cosine_distance(sentence[i:i + 1], sentence[j:j + 1])) if name == "sentence" \
                else chamfer(tokens[i], tokens[j])

        side, action_d, rank, same = [], [], [], []
        for k, text in enumerate(sided):
            i = texts.index(text)
            others = [dist(i, j) for j, other in enumerate(texts) if action[other] != action[text]]
            same += [dist(i, j) for j, other in enumerate(texts) if action[other] == action[text] and other != text]
            side.append(dist(i, len(texts) + k))
            if others:
                rank.append(sum(d < side[-1] for d in others) / len(others))
            action_d.extend(others)
        if not action_d:
            raise ValueError("every caption has the same action: nothing to compare a side swap with")
        mean_side, mean_action = sum(side) / len(side), sum(action_d) / len(action_d)
        out[name] = {"side": mean_side, "action": mean_action, "ratio": mean_side / mean_action,
                     "same_action": sum(same) / len(same) if same else float("nan"),
                     "rank": sum(rank) / len(rank), "captions": len(sided)}
    return out
