"""``read_motion``: any supported motion file into a ``RigMotion``, chosen by suffix.

- ``.bvh``: ``omg.io.bvh.read_bvh`` (option ``scale``);
- ``.json`` / ``.txt``: a DeepMimic motion (option ``character``, default the ``char_*.txt``
  beside it);
- ``.amc``: ASF/AMC (options ``asf``, default ``NN.asf`` beside ``NN_MM.amc``, ``fps``
  (default 120), ``scale``).
"""

from __future__ import annotations

from pathlib import Path

from omg.errors import UsageError
from omg.io.rig import RigMotion

MOTION_SUFFIXES = (".bvh", ".amc", ".json", ".txt")


def read_motion(path: str | Path, *, what: str = "", **options) -> RigMotion:
    """Read a motion file; ``options`` go to the format's reader (unknown ones are an error). ``what``
    (the option that named the file, e.g. "--from_motion") leads the line when it is no file to read."""
    path = Path(path)
    suffix = path.suffix.lower()
    allowed = {".bvh": {"scale"}, ".amc": {"asf", "fps", "scale"}, ".json": {"character"}, ".txt": {"character"}}
    if suffix not in allowed:
        raise UsageError(f"{path}: unknown motion format {suffix!r}; supported: {', '.join(MOTION_SUFFIXES)}")
    unknown = set(options) - allowed[suffix]
    if unknown:
        raise UsageError(f"{path}: option(s) {', '.join(sorted(unknown))} do not apply to {suffix} files "
                         f"(these take {', '.join(sorted(allowed[suffix]))})")
    if suffix == ".bvh":
        from omg.io.bvh import read_bvh

        return read_bvh(path, **options, what=what)
    if suffix == ".amc":
        from omg.io.asf_amc import read_amc

        return read_amc(path, **{k: v for k, v in options.items() if v is not None}, what=what)
    from omg.io.deepmimic import read_deepmimic

    return read_deepmimic(path, **options, what=what)
