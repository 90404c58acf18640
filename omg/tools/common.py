"""Helpers the tool commands share; output folders removed again when a command fails are
``omg.files.removing_created``, UTF-8 text files are read by ``omg.files.read_text``."""

from __future__ import annotations


def last_line(message: str) -> str:
    """The last non-empty line of a message, e.g. the exception line of a traceback a worker sent."""
    lines = [line for line in message.strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else message
