"""The ``omg`` command: a thin front that dispatches to Lightning or to a tool command.

``omg fit|validate|test|predict`` go to LightningCLI (configs with ``class_path`` /
``init_args``, ``--print_config``, dotted overrides). Every other subcommand is a function
taking ``argv`` in the module named in ``COMMANDS``, imported only when used so that
``omg --help`` stays fast. Plugins load before anything is parsed, so a config can name
their components. Bad user input ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import math
import os
import re
import shutil
import sys
import warnings
from pathlib import Path
from typing import Iterator

from omg.errors import UsageError

LIGHTNING = {
    "fit": "train a model (a LightningModule and data from a YAML config)",
    "validate": "run the validation loop of a config on a checkpoint",
    "test": "run the test loop of a config on a checkpoint",
    "predict": "run the prediction loop of a config on a checkpoint",
}

COMMANDS = {  # name -> (module:function, one-line description)
    "shards": ("omg.data.commands:shards_main", "build, synthesise and inspect WebDataset motion shards"),
    "plugins": ("omg.cli:plugins_main", "list every registry and the components registered in it"),
    "generate": ("omg.generate:main", "sample motions from a checkpoint (unconditional, or from text prompts)"),
    "bench": ("omg.bench:main", "measure data loading, training and sampling speed and memory"),
    "convert-ckpt": ("omg.lit.checkpoint:main", "turn a DeepSpeed/Lightning checkpoint into one fp32 (or EMA) safetensors file"),
    "export": ("omg.io.export:main", "write BVH files and rendered previews of motions (npy joint positions or features)"),
}


def number(kind: type, minimum: float | None = None, above: float | None = None, maximum: float | None = None):
    """An argparse ``type``: an int or a finite float, optionally bounded (``above``: exclusive)."""
    noun = "an integer" if kind is int else "a finite number"
    bounds = [f">= {minimum}" if minimum is not None else "", f"> {above}" if above is not None else "",
              f"<= {maximum}" if maximum is not None else ""]
    wanted = " ".join([noun, " and ".join(b for b in bounds if b)]).strip()

    def convert(text: str):
        value = kind(text)  # a ValueError here: argparse's "invalid int value: 'x'"
        if not math.isfinite(value) or (minimum is not None and value < minimum) or (
                above is not None and value <= above) or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"expected {wanted}, got {text!r}")
        return value

    convert.__name__ = kind.__name__  # argparse names the type in some messages
    return convert


positive_int = number(int, minimum=1)
nonneg_int = number(int, minimum=0)
seed_int = number(int, minimum=0, maximum=2**63 - 1)
positive_float = number(float, above=0)
nonneg_float = number(float, minimum=0)
finite_float = number(float)


class ToolParser(argparse.ArgumentParser):
    """argparse for tool commands: errors raise instead of printing usage and exiting.

    Numbers are checked: ``type=int`` options take integers >= 0 and ``type=float`` options
    finite numbers >= 0 (no NaN, inf or negative counts, sizes and rates); pass a ``number(...)``
    type such as ``finite_float`` or ``positive_int`` for other ranges.
    """

    def add_argument(self, *args, **kwargs):
        if kwargs.get("type") is int:
            kwargs["type"] = nonneg_int
        elif kwargs.get("type") is float:
            kwargs["type"] = nonneg_float
        return super().add_argument(*args, **kwargs)

    def error(self, message: str):
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def read_text(path: str | Path, what: str) -> str:
    """A UTF-8 text file's contents; a missing file, a folder or another encoding is a UsageError."""
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"{what} {path}: is a folder, not a file")
    if not path.is_file():
        raise UsageError(f"{what} {path}: no such file")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise UsageError(f"{what} {path}: cannot be read ({e.strerror or e})") from None
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (Windows editors) is not part of the text
    except UnicodeDecodeError as e:
        raise UsageError(f"{what} {path}: not a UTF-8 text file (byte 0x{data[e.start]:02x} at offset {e.start}); "
                         "save it as UTF-8") from None


def check_output_dir(path: str | Path, what: str = "--out") -> Path:
    """``path`` can be (or already is) a folder: neither it nor a parent is an existing file."""
    path = Path(path)
    for p in [path, *path.parents]:
        if p.exists() and not p.is_dir():
            where = "" if p == path else f" (its parent {p} is a file)"
            raise UsageError(f"{what} {path}: not a folder{where}; choose a folder path for the output")
        if p.exists():
            if not os.access(p, os.W_OK | os.X_OK):
                raise UsageError(f"{what} {path}: {p} is not writable")
            break
    return path


@contextlib.contextmanager
def removing_created(*dirs: str | Path) -> Iterator[None]:
    """Folders (and their missing parents) this block may create are removed if it fails, with
    everything in them; folders that existed before it, the user's, are never touched."""
    created = []
    for d in map(Path, dirs):
        missing = [p for p in [d, *d.parents] if not p.exists()]
        if missing and missing[-1] not in created:
            created.append(missing[-1])  # the topmost folder the block would create
    try:
        yield
    except Exception:
        for d in created:
            if d.is_dir() and not d.is_symlink():
                shutil.rmtree(d, ignore_errors=True)
        raise


def _usage() -> str:
    width = max(map(len, [*LIGHTNING, *COMMANDS]))
    lines = ["usage: omg <command> [options]   (omg <command> --help for its options)", "", "commands:"]
    for name, desc in LIGHTNING.items():
        lines.append(f"  {name:<{width}}  {desc}")
    for name, (_, desc) in COMMANDS.items():
        lines.append(f"  {name:<{width}}  {desc}")
    return "\n".join(lines)


def plugins_main(argv: list[str]) -> None:
    from omg.registry import ALL, load_plugins

    ToolParser(prog="omg plugins", description=COMMANDS["plugins"][1]).parse_args(argv)
    loaded = load_plugins()
    print(f"plugins (entry-point group omg.plugins): {', '.join(loaded) or 'none installed'}")
    for title, registry in ALL.items():
        print(f"\n{title}:")
        for name in registry.names() or ["(none)"]:
            print(f"  {name:<24} {registry.describe(name) if name in registry else ''}")


def lightning_main(argv: list[str]) -> None:
    import logging

    from jsonargparse import ArgumentError
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from omg.data.datamodule import TooManyBadSamples
    from omg.lit.cli import OmgLightningCLI

    logging.getLogger("lightning.fabric.utilities.seed").setLevel(logging.WARNING)
    # Lightning's advertising and its own deprecation notices are not the user's business
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(lambda r: "💡 Tip" not in r.getMessage())
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)` is deprecated.*")
    _check_config_files(argv)
    sys.argv = ["omg", *argv]  # LightningCLI reads sys.argv; passing args as well makes it warn
    try:
        OmgLightningCLI()
    except UnicodeDecodeError as e:  # a config file given to another key (--data FILE, ...)
        binary = [f"{flag} {value}" for flag, value in _file_arguments(argv)
                  if flag != "--ckpt_path" and not _is_utf8(value)]
        which = f"{binary[0]}: not a UTF-8 text (YAML) file" if binary else "a file is not UTF-8 text"
        raise UsageError(f"{which} ({e.reason} at offset {e.start}); save it as UTF-8") from None
    except ArgumentError as e:
        raise UsageError(jsonargparse_reason(str(e))) from None
    except MisconfigurationException as e:  # e.g. a GPU config on a machine without one
        raise UsageError(f"{str(e).strip().splitlines()[0]} (override trainer settings with --trainer.KEY VALUE, "
                         "e.g. --trainer.accelerator cpu)") from None
    except ValueError as e:  # a component's own UsageError, wrapped by jsonargparse's union check
        if "Does not validate against any of the Union subtypes" not in str(e):
            raise
        raise UsageError(jsonargparse_reason(str(e))) from None
    except SIGTERMException as e:  # Lightning's loops stop at a step boundary and exit "successfully"
        stop = getattr(e, "omg_stop", None) or {"step": "?", "checkpoint": None, "requeued": False}
        where = (f"checkpoint {stop['checkpoint']} (resume with --ckpt_path last)" if stop["checkpoint"]
                 else "no checkpoint was written")
        if stop["requeued"]:
            print(f"omg: requeued by SLURM at step {stop['step']}; {where}", file=sys.stderr)
            raise SystemExit(0) from None
        print(f"omg: interrupted by SIGTERM at step {stop['step']}; {where}", file=sys.stderr)
        raise SystemExit(SIGTERM_EXIT) from None
    except TooManyBadSamples as e:  # from a data worker, wrapped in the worker's traceback
        raise UsageError(last_line(str(e)).removeprefix(f"{TooManyBadSamples.__module__}.TooManyBadSamples: ")) from None
    except RuntimeError as e:
        if "DataLoader timed out" not in str(e):
            raise
        seconds = re.search(r"after (\S+) seconds", str(e))
        raise UsageError(f"a data worker delivered no batch in data.timeout={seconds[1] if seconds else '?'} s: a stalled "
                         "read or worker; check the shard storage, or raise data.timeout (0 waits forever)") from None


SIGTERM_EXIT = 128 + 15  # the shell's code for a process ended by SIGTERM


def last_line(message: str) -> str:
    lines = [line for line in message.strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else message


def _file_arguments(argv: list[str]) -> list[tuple[str, str]]:
    """(flag, value) of every ``--flag VALUE`` / ``--flag=VALUE`` whose value is an existing file."""
    pairs = []
    for i, arg in enumerate(argv):
        flag, sep, value = arg.partition("=")
        if flag.startswith("-") and not sep and i + 1 < len(argv):
            value = argv[i + 1]
        if flag.startswith("-") and value and Path(value).is_file():
            pairs.append((flag, value))
    return pairs


def _is_utf8(path: str) -> bool:
    try:
        Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return False
    except OSError:
        return True  # not ours to judge: jsonargparse reports it
    return True


def _check_config_files(argv: list[str]) -> None:
    """``--config FILE`` must be a UTF-8 text file (jsonargparse reads it as such and fails with a
    traceback otherwise); missing files and folders are left to jsonargparse's own message."""
    for flag, value in _file_arguments(argv):
        if flag in ("--config", "-c"):
            read_text(value, flag)


_STRUCTURE = ("Subtypes:", "Errors:", "Given value", "Does not validate", "Problem with given class_path",
              "Expected a <class 'NoneType'>")


def jsonargparse_reason(message: str) -> str:
    """jsonargparse nests its reasons over many lines; keep the dotted key and the first real reason."""
    keys = re.findall(r'Parser key "([^"]+)"', message)
    lines = [ln.strip(" -") for ln in message.splitlines()]
    reasons = [ln for ln in lines if ln and "Parser key" not in ln and not ln.startswith(_STRUCTURE)]
    reason = reasons[0] if reasons else re.sub(r'^Parser key "[^"]+":\s*', "", message.strip().splitlines()[0])
    if "unrecognized arguments" in reason or "not expected" in reason:
        reason += "; see the valid keys with `omg fit --config FILE --print_config`"
    return f"{'.'.join(keys)}: {reason}" if keys else reason


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return
    command, rest = argv[0], argv[1:]
    try:
        from omg.registry import load_plugins

        load_plugins()
        if command in LIGHTNING:
            lightning_main([command, *rest])
        elif command in COMMANDS:
            module, function = COMMANDS[command][0].split(":")
            getattr(importlib.import_module(module), function)(rest)
        else:
            known = ", ".join([*LIGHTNING, *COMMANDS])
            raise UsageError(f"unknown command {command!r}; commands: {known}")
    except UnicodeDecodeError as e:  # a text file in another encoding, read where no check names it
        _usage_exit(f"a file is not UTF-8 text ({e.reason} at offset {e.start}); save it as UTF-8")
    except UsageError as e:
        _usage_exit(str(e))


def _usage_exit(message: str) -> None:
    """One line on stderr, exit code 2: messages that quote a file or an error can hold newlines."""
    message = re.sub(r"\s*\n\s*", " ", message.strip())
    sys.stdout.flush()
    print(f"omg: error: {message}", file=sys.stderr)
    raise SystemExit(2) from None


if __name__ == "__main__":
    main()
