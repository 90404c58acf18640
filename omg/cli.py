"""The ``omg`` command: a thin front that dispatches to Lightning or to a tool command.

``omg fit|validate|test|predict`` go to LightningCLI (configs with ``class_path`` /
``init_args``, ``--print_config``, dotted overrides). Every other subcommand is a function
taking ``argv`` in the module named in ``COMMANDS``, imported only when used so that
``omg --help`` stays fast. Plugins load before anything is parsed, so a config can name
their components. Bad user input ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys

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


class ToolParser(argparse.ArgumentParser):
    """argparse for tool commands: errors raise instead of printing usage and exiting."""

    def error(self, message: str):
        raise UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


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

    from omg.lit.cli import OmgLightningCLI

    logging.getLogger("lightning.fabric.utilities.seed").setLevel(logging.WARNING)
    sys.argv = ["omg", *argv]  # LightningCLI reads sys.argv; passing args as well makes it warn
    try:
        OmgLightningCLI()
    except ArgumentError as e:
        raise UsageError(jsonargparse_reason(str(e))) from None
    except MisconfigurationException as e:  # e.g. a GPU config on a machine without one
        raise UsageError(f"{str(e).strip().splitlines()[0]} (override trainer settings with --trainer.KEY VALUE, "
                         "e.g. --trainer.accelerator cpu)") from None
    except ValueError as e:  # a component's own UsageError, wrapped by jsonargparse's union check
        if "Does not validate against any of the Union subtypes" not in str(e):
            raise
        raise UsageError(jsonargparse_reason(str(e))) from None


_STRUCTURE = ("Subtypes:", "Errors:", "Given value", "Does not validate", "Problem with given class_path",
              "Expected a <class 'NoneType'>")


def jsonargparse_reason(message: str) -> str:
    """jsonargparse nests its reasons over many lines; keep the dotted key and the first real reason."""
    keys = re.findall(r'Parser key "([^"]+)"', message)
    lines = [ln.strip(" -") for ln in message.splitlines()]
    reasons = [ln for ln in lines if ln and "Parser key" not in ln and not ln.startswith(_STRUCTURE)]
    reason = reasons[0] if reasons else message.splitlines()[0]
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
    except UsageError as e:
        print(f"omg: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
