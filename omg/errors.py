"""The one exception type for bad user input (config values, paths, prompts, files).

The CLI prints a ``UsageError`` as a single line and exits with code 2; anything else is a
bug and keeps its traceback.
"""


class UsageError(ValueError):
    """Bad input from the user; the message names the bad value and how to fix it."""


class PeerLost(UsageError):
    """A multi-process run broken by another rank (a lost peer, a collective's timeout): one line, after which the
    process ends at once. Its process group's threads would otherwise be torn down at the interpreter's exit with a
    peer gone, where one can abort the process ("terminate called without an active exception": SIGABRT in place of
    exit code 2); the run's checkpoints and loggers were closed when Lightning tore the run down."""
