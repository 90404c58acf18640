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
