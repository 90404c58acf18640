"""``python -m omg``: the ``omg`` command (``omg.cli``), for an environment without the console script."""

from omg.cli import main

if __name__ == "__main__":
    main()
