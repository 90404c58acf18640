"""The ``omg`` command: a thin front that dispatches to Lightning or to a tool command.

``omg fit|validate|test|predict`` go to LightningCLI (configs with ``class_path`` /
``init_args``, ``--print_config``, dotted overrides). Every other subcommand is a typed function
in ``omg.tools`` exposed through jsonargparse as well (``omg.tools.args``): the module named in
``COMMANDS`` is imported only when used, so that ``omg --help`` stays fast. Plugins load before
anything is parsed, so a config can name their components. Bad user input ends with one line
on stderr, ``omg: error: <key>: <reason>``, and exit code 2.
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings

from omg.errors import PeerLost, UsageError

LIGHTNING = {
    "fit": "train a model (a LightningModule and data from a YAML config)",
    "validate": "run the validation loop of a config on a checkpoint",
    "test": "run the test loop of a config on a checkpoint",
    "predict": "run the prediction loop of a config on a checkpoint",
}

COMMANDS = {  # name -> (module:function taking argv, one-line description)
    "shards": ("omg.tools.shards:main", "build, synthesise and inspect WebDataset motion shards"),
    "plugins": ("omg.cli:plugins_main", "list every registry and the components registered in it"),
    "generate": ("omg.tools.generate:main", "sample motions from a checkpoint (unconditional, or from text prompts)"),
    "bench": ("omg.tools.bench:main", "measure data loading, training and sampling speed and memory; plan GPU runs"),
    "convert-ckpt": ("omg.tools.convert:main",
                     "turn a DeepSpeed/Lightning checkpoint into one fp32 (or EMA) safetensors file"),
    "export": ("omg.tools.export:main",
               "write BVH files and rendered previews of motions (npy joint positions or features)"),
    "transfer": ("omg.tools.habit:main",
                 "move a quadruped motion onto another species with its habits (habit VQ-VAE + flow prior)"),
    "serve": ("omg.tools.serve:main", "a local page and HTTP API over checkpoints (generate, transfer, 3D viewer)"),
    "joint-map": ("omg.tools.joint_map:main", "start a joint map (YAML) for a rig no built-in map fits, from the "
                                             "closest one"),
    "plot": ("omg.tools.plot:main", "draw a run folder's training curves (losses, learning rate, evaluation) to a PNG"),
}

SIGTERM_EXIT = 128 + 15  # the shell's code for a process ended by SIGTERM
SIGINT_EXIT = 128 + 2  # ... by SIGINT (Ctrl-C)
SIGPIPE_EXIT = 128 + 13  # ... and by SIGPIPE (a reader that closed our stdout)


def _usage() -> str:
    width = max(map(len, [*LIGHTNING, *COMMANDS]))
    lines = ["usage: omg <command> [options]   (omg <command> --help for its options)", "", "commands:"]
    for name, desc in LIGHTNING.items():
        lines.append(f"  {name:<{width}}  {desc}")
    for name, (_, desc) in COMMANDS.items():
        lines.append(f"  {name:<{width}}  {desc}")
    return "\n".join(lines)


def plugins() -> None:
    """List every registry and the components registered in it (plugins: entry-point group omg.plugins)."""
    from omg.registry import ALL, load_plugins

    loaded = load_plugins()
    print(f"plugins (entry-point group omg.plugins): {', '.join(loaded) or 'none installed'}")
    for title, registry in ALL.items():
        print(f"\n{title}:")
        for name in registry.names() or ["(none)"]:
            print(f"  {name:<24} {registry.describe(name) if name in registry else ''}")


def plugins_main(argv: list[str]) -> None:
    from omg.tools.args import run

    run(plugins, argv, "omg plugins")


def lightning_main(argv: list[str]) -> None:
    import logging

    from jsonargparse import ArgumentError
    from lightning.fabric.utilities.exceptions import MisconfigurationException
    from lightning.pytorch.utilities.exceptions import SIGTERMException

    from omg.data.loaders import TooManyBadSamples
    from omg.tools.args import check_config_files, explain, file_arguments, is_utf8
    from omg.tools.common import last_line
    from omg.tools.lightning import FIT_HINT, OmgLightningCLI

    logging.getLogger("lightning.fabric.utilities.seed").setLevel(logging.WARNING)
    # Lightning's advertising and its own deprecation notices are not the user's business; the CLI
    # entry point is the one place that sets global filters
    logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(lambda r: "💡 Tip" not in r.getMessage())
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)` is deprecated.*")
    # the frozen DiT and text backbones stay in eval mode on purpose
    warnings.filterwarnings("ignore", message=r".*module\(s\) in eval mode at the start of training.*")
    # omg's stream splits every epoch exactly among the loader workers, so its length is exact
    warnings.filterwarnings("ignore", message=".*IterableDataset.*has `__len__` defined.*")
    check_config_files(argv)
    # the command line as Lightning's launchers see it: `--trainer.devices N` on one machine starts ranks
    # 1..N-1 by running it again, as `python -m MODULE ARGS` when omg was started as a module (`python -m
    # omg`, `python -m omg.cli`), else as `python ABSPATH(sys.argv[0]) ARGS`: the program itself, so
    # sys.argv[0] stays what it is (the console script's path), not a name that is no file
    sys.argv = [sys.argv[0], *argv]
    try:
        OmgLightningCLI(argv[0], argv[1:]).run_command()
    except UnicodeDecodeError as e:  # a config file given to another key (--data FILE, ...)
        binary = [f"{flag} {value}" for flag, value in file_arguments(argv)
                  if flag != "--ckpt_path" and not is_utf8(value)]
        which = f"{binary[0]}: not a UTF-8 text (YAML) file" if binary else "a file is not UTF-8 text"
        raise UsageError(f"{which} ({e.reason} at offset {e.start}); save it as UTF-8") from None
    except ArgumentError as e:
        raise UsageError(explain(e, hint=FIT_HINT)) from None
    except MisconfigurationException as e:  # e.g. a GPU config on a machine without one
        raise UsageError(f"{str(e).strip().splitlines()[0]} (override trainer settings with --trainer.KEY VALUE, "
                         "e.g. --trainer.accelerator cpu)") from None
    except SIGTERMException as e:  # Lightning's loops stop at a step boundary and exit "successfully"
        stop = {"step": "?", "checkpoint": None, "requeued": False, "signal": "SIGTERM",
                **(getattr(e, "omg_stop", None) or {})}  # omg.callbacks.run.InterruptCheckpoint
        where = (f"checkpoint {stop['checkpoint']} (resume with --ckpt_path last)" if stop["checkpoint"]
                 else "no checkpoint was written")
        if "during" in stop:  # omg test: omg.callbacks.run.stop_if_signalled
            print(f"omg: interrupted by SIGTERM during {stop['during']}; no report was written", file=sys.stderr)
            raise SystemExit(SIGTERM_EXIT) from None
        if stop["requeued"]:
            print(f"omg: requeued by SLURM at step {stop['step']}; {where}", file=sys.stderr)
            raise SystemExit(0) from None
        if stop["signal"] == "SIGINT":
            print(f"omg: interrupted by Ctrl-C at step {stop['step']}; {where}", file=sys.stderr)
            raise SystemExit(SIGINT_EXIT) from None
        print(f"omg: interrupted by SIGTERM at step {stop['step']}; {where}", file=sys.stderr)
        raise SystemExit(SIGTERM_EXIT) from None
    except TooManyBadSamples as e:  # from a data worker: torch re-raises it with the worker's traceback as its text
        prefix = f"{TooManyBadSamples.__module__}.TooManyBadSamples: "
        raise UsageError(last_line(str(e)).removeprefix(prefix)) from None


def main(argv: list[str] | None = None) -> None:
    try:
        try:
            _run(sys.argv[1:] if argv is None else argv)
        finally:
            sys.stdout.flush()  # here rather than at exit, so that a closed stdout is handled below
    except BrokenPipeError:
        _stdout_closed()
    except KeyboardInterrupt:  # Ctrl-C before a run sets its own handler: reading configs, fetching manifests
        print("omg: interrupted by Ctrl-C", file=sys.stderr)
        raise SystemExit(SIGINT_EXIT) from None


def _run(argv: list[str]) -> None:
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
        _usage_exit(str(e), at_once=isinstance(e, PeerLost))


def _stdout_closed() -> None:
    """The reader of stdout left early (``omg plugins | head -1``): it has what it wanted, so end
    quietly, with the status of a process that SIGPIPE ended, as ``yes | head -1`` does."""
    # what is still buffered would fail again when Python flushes stdout at exit, with a message
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    raise SystemExit(SIGPIPE_EXIT) from None


def _usage_exit(message: str, at_once: bool = False) -> None:
    """One line on stderr, exit code 2: messages that quote a file or an error can hold newlines. ``at_once``
    (``PeerLost``): the process ends without the interpreter's teardown."""
    message = " ".join(line.strip() for line in message.strip().splitlines() if line.strip())
    sys.stdout.flush()
    print(f"omg: error: {message}", file=sys.stderr)
    if at_once:
        sys.stderr.flush()
        os._exit(2)
    raise SystemExit(2) from None


if __name__ == "__main__":
    main()
