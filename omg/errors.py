"""The one exception type for bad user input (config values, paths, prompts, files).

The CLI prints a ``UsageError`` as a single line and exits with code 2; anything else is a
bug and keeps its traceback.
"""


class UsageError(ValueError):
    """Bad input from the user; the message names the bad value and how to fix it."""
