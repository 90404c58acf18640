"""One argument system for ``omg``: typed functions exposed through jsonargparse, errors as one line.

Each tool command is a typed Python function whose docstring documents every parameter under
``Args:``; ``function_parser`` turns it into a jsonargparse parser with
``add_function_arguments``, as LightningCLI does for ``omg fit``: the same ``--key value`` /
``--key=value`` options with underscores, ``--config FILE`` and ``--print_config``, numbers
checked by jsonargparse's types (``PositiveInt``, ``restricted_number_type``). Two things type
hints alone do not give: a variadic positional (``omg generate PROMPT ...``: jsonargparse adds
signature parameters as options or as one-value positionals, so that one parameter is added
with ``nargs``), and ``bool`` parameters as flags without a value (``--preview`` /
``--no_preview``, jsonargparse's ``ActionYesNo``).

Bad input is one line, ``<key>: <reason>``. ``KeyedErrors`` marks each exception a value check
raises with the key, the action (and so the type) and the value it checked; ``explain`` builds
the line from those marks, from a ``UsageError`` a component raised, or from the innermost
exception of the chain: never from the text of jsonargparse's nested messages.
"""

from __future__ import annotations

import argparse
import inspect
import math
import shlex
import sys
import types
import typing
from pathlib import Path, PurePath
from typing import Any, Callable

from jsonargparse import ActionConfigFile, ActionSubCommands, ActionYesNo, ArgumentParser, Namespace
from jsonargparse.typing import NonNegativeInt, PositiveInt, restricted_number_type

from omg.errors import UsageError
from omg.files import read_text

# -- numbers ----------------------------------------------------------------------------------
WANTED: dict[type, str] = {PositiveInt: "an integer >= 1", NonNegativeInt: "an integer >= 0"}  # type -> its wording


def number_type(name: str, base: type, restrictions: list[tuple[str, float]], wanted: str) -> type:
    """A jsonargparse ``restricted_number_type`` and how an error message names what it accepts."""
    kind = restricted_number_type(name, base, restrictions)
    WANTED[kind] = wanted
    return kind


# NaN fails every comparison, so a bound on each side refuses it; jsonargparse's PositiveFloat
# and NonNegativeFloat accept inf, which is no count, size, rate or scale
Seed = number_type("Seed", int, [(">=", 0), ("<", 2**63)], "an integer in [0, 2^63)")
FiniteFloat = number_type("FiniteFloat", float, [(">", -math.inf), ("<", math.inf)], "a finite number")
PositiveFiniteFloat = number_type("PositiveFiniteFloat", float, [(">", 0.0), ("<", math.inf)], "a finite number > 0")
Fraction = number_type("Fraction", float, [(">=", 0.0), ("<", 1.0)], "a number in [0, 1)")

__all__ = ["FiniteFloat", "Fraction", "NonNegativeInt", "PositiveFiniteFloat", "PositiveInt", "Seed", "number_type",
           "function_parser", "run", "run_subcommands", "explain", "KeyedErrors", "check_config_files",
           "underscore_options"]


# -- errors -----------------------------------------------------------------------------------
_MARK = "_omg_argument"  # (key, action, value) of the check that raised an exception


def _mark(error: BaseException, key: str, action, value) -> None:
    if not hasattr(error, _MARK):  # the innermost check that saw it names it
        try:
            setattr(error, _MARK, (key, action, value))
        except AttributeError:
            pass


def _marked_check_type(self, value, **kwargs):
    """An action's ``_check_type_``, marking what it raises with the action's key and the value."""
    try:
        return type(self)._check_type_(self, value, **kwargs)
    except (TypeError, ValueError) as e:
        _mark(e, self.dest, self, value)
        raise


def _watch(parser: ArgumentParser) -> None:
    """Mark the errors of every value check of ``parser`` and of its subcommands' parsers."""
    for action in parser._actions:
        if isinstance(action, ActionSubCommands):
            for subparser in action.choices.values():
                _watch(subparser)
        elif hasattr(type(action), "_check_type_") and "_check_type_" not in vars(action):
            action._check_type_ = types.MethodType(_marked_check_type, action)  # deepcopy rebinds it to the copy


class KeyedErrors:
    """A mixin for jsonargparse parsers: every exception a value check raises carries the key it
    checked (``explain`` reads it). Values from the command line are checked by their actions
    (watched before parsing); values from config files, defaults and nested class parsers (which
    jsonargparse makes of the parent's class) go through ``_check_value_key``. Where a jsonargparse
    version calls neither, errors lose their key and ``explain`` falls back to the innermost reason."""

    def parse_args(self, args=None, *rest, **kwargs):
        _watch(self)
        args = underscore_options(sys.argv[1:] if args is None else list(args), option_names(self))
        return super().parse_args(args, *rest, **kwargs)

    def parse_object(self, *args, **kwargs):
        _watch(self)
        return super().parse_object(*args, **kwargs)

    def _check_value_key(self, action, value, key, *args, **kwargs):
        try:
            return super()._check_value_key(action, value, key, *args, **kwargs)
        except (TypeError, ValueError) as e:
            if not isinstance(action, ActionSubCommands):  # its subcommand's parser names the key
                _mark(e, key, action, value)
            raise


# -- option spellings ----------------------------------------------------------------------------
def option_names(parser: ArgumentParser) -> set[str]:
    """Every long option of ``parser`` and of its subcommands' parsers."""
    names: set[str] = set()
    for action in parser._actions:
        if isinstance(action, ActionSubCommands):
            for subparser in action.choices.values():
                names |= option_names(subparser)
        names.update(s for s in action.option_strings if s.startswith("--"))
    return names


def underscore_options(argv: list[str], known: set[str]) -> list[str]:
    """``argv`` with option names spelled with dashes (``--num-samples``, ``--trainer.max-steps``,
    the earlier CLI's spelling) in the underscore spelling the parsers know; help shows only that one.

    A token is rewritten only where it starts with ``--``, is no option as it is spelled, and its
    underscore spelling is an option or, dotted, extends one (``--model.init-args.ema-decay``
    extends ``--model``, whose keys come from its class). So values stay as they are: what follows
    ``=``, everything after a bare ``--``, and a value such as the prompt ``--a-b`` (no option
    ``--a_b``); a value spelled like a dashed option would be rewritten, so pass such a value as
    ``--option=VALUE``."""
    out = []
    for i, arg in enumerate(argv):
        if arg == "--":
            return out + argv[i:]
        name, sep, value = arg.partition("=")
        if name.startswith("--") and "-" in name[2:] and name not in known:
            underscored = "--" + name[2:].replace("-", "_")
            parts = underscored.split(".")
            if any(".".join(parts[:k]) in known for k in range(len(parts), 0, -1)):
                arg = underscored + sep + value
        out.append(arg)
    return out


class OmgArgumentParser(KeyedErrors, ArgumentParser):
    """The tools' jsonargparse parser."""


def _chain(error: BaseException) -> list[BaseException]:
    """``error`` and what caused it, outermost first."""
    chain: list[BaseException] = []
    while error is not None and all(error is not e for e in chain):
        chain.append(error)
        error = error.__cause__ or (None if error.__suppress_context__ else error.__context__)
    return chain


def _typehint(action) -> Any:
    return getattr(action, "_typehint", None) or getattr(action, "type", None)


def describe(hint) -> str | None:
    """What a value of type ``hint`` must be, in words; None for types without a short wording
    (classes, whose own errors say more)."""
    if isinstance(hint, type) and hint in WANTED:
        return WANTED[hint]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        words = [describe(a) for a in args if a is not type(None)]
        return " or ".join(words) if words and all(words) else None
    if origin is typing.Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (list, tuple) and args and (item := describe(args[0])):
        return f"a list such as [a, b] with each item {item}"
    if origin is dict or hint is dict:
        return "a mapping such as {key: value}"
    words = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if isinstance(hint, type) and hint in words:
        return words[hint]
    if isinstance(hint, type) and issubclass(hint, PurePath):
        return "a path"
    return None


def _first_line(error: BaseException) -> str:
    text = str(error.args[0]) if isinstance(error, KeyError) and error.args else str(error)  # KeyError quotes
    lines = [line.strip(" -") for line in text.splitlines() if line.strip(" -")]
    return lines[0] if lines else type(error).__name__


def _is_subclass_action(action) -> bool:
    """The action takes a class (``class_path`` / ``init_args``), not a plain value."""
    hint = _typehint(action)
    hints = [h for h in typing.get_args(hint) if h is not type(None)] or [hint]
    plain = (bool, int, float, str, bytes, PurePath, list, tuple, dict, set)
    return any(inspect.isclass(h) and not issubclass(h, plain) for h in hints)


def explain(error: BaseException, hint: str = "") -> str:
    """One line for a parsing error: ``<key>: <reason>``.

    A UsageError in the chain (a component refusing its value) is the reason as it is. Otherwise
    the marks of the failed checks give the key, joined outer to inner (``model.init_args.lr``),
    and the innermost mark's type and value the reason (``expected an integer >= 1, got '-2'``);
    for types without a wording, the innermost exception's first line. ``hint`` is added to
    errors that name no key (unrecognized arguments, unknown config keys, missing arguments)."""
    chain = _chain(error)
    usage = next((e for e in chain if isinstance(e, UsageError)), None)
    if usage is not None:
        return str(usage)
    marks = [getattr(e, _MARK) for e in chain if hasattr(e, _MARK)]
    parts: list[tuple[str, Any]] = []
    for key, action, _ in marks:
        if not parts or parts[-1][0] != key:
            parts.append((key, action))
    key = ""
    for i, (name, action) in enumerate(parts):
        key = name if i == 0 else f"{key}{'.init_args.' if _is_subclass_action(parts[i - 1][1]) else '.'}{name}"
    reason = None
    if marks:
        _, action, value = marks[-1]
        wanted = describe(_typehint(action))
        if wanted and isinstance(value, (str, int, float, bool, list, dict, PurePath, type(None))):
            reason = f"expected {wanted}, got {value!r}"
    if reason is None:
        reason = _first_line(chain[-1])
    if key:
        return f"{key}: {reason}"
    return f"{reason}; {hint}" if hint else reason


# -- config files -----------------------------------------------------------------------------
def file_arguments(argv: list[str]) -> list[tuple[str, str]]:
    """(flag, value) of every ``--flag VALUE`` / ``--flag=VALUE`` whose value is an existing file."""
    pairs = []
    for i, arg in enumerate(argv):
        flag, sep, value = arg.partition("=")
        if flag.startswith("-") and not sep and i + 1 < len(argv):
            value = argv[i + 1]
        if flag.startswith("-") and value and Path(value).is_file():
            pairs.append((flag, value))
    return pairs


def is_utf8(path: str) -> bool:
    try:
        Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return False
    except OSError:
        return True  # not ours to judge: jsonargparse reports it
    return True


def check_config_files(argv: list[str]) -> None:
    """``--config FILE`` must be a UTF-8 text file: jsonargparse reads it as such and fails with a
    traceback otherwise, and names neither the option nor the file for a folder. A value that
    is no path (``--config '{key: value}'``, a config given inline) is left to jsonargparse."""
    for i, arg in enumerate(argv):
        flag, sep, value = arg.partition("=")
        if flag not in ("--config", "-c") or (not sep and i + 1 == len(argv)):
            continue
        value = value if sep else argv[i + 1]
        if Path(value).exists() or not any(c in value for c in "{}[]:\n"):
            check_config_text(read_text(value, flag), f"{flag} {value}")


def check_config_text(text: str, what: str) -> None:
    """A config file's text is a YAML mapping: jsonargparse reports a syntax error without the
    file or the line, and an empty file as "Unexpected config"."""
    import yaml

    try:
        config = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(e, "problem", None) or _first_line(e)
        raise UsageError(f"{what}: not valid YAML{where}: {problem}") from None
    if config is None:
        raise UsageError(f"{what}: the file is empty (or only comments); give the settings as key: value lines")
    if not isinstance(config, dict):
        raise UsageError(f"{what}: a config file holds key: value settings, got a {type(config).__name__}")


# -- functions as commands --------------------------------------------------------------------
RECORDED = "command"  # a parameter of this name is not an option: it receives the command line


def _docs(function: Callable) -> tuple[str, dict[str, str]]:
    import docstring_parser

    doc = docstring_parser.parse(inspect.getdoc(function) or "")
    text = "\n\n".join(part for part in (doc.short_description, doc.long_description) if part)
    return text, {p.arg_name: p.description or "" for p in doc.params}


def function_parser(function: Callable, prog: str, positional: str | None = None, nargs: str = "*",
                    as_positional: bool = False) -> ArgumentParser:
    """A jsonargparse parser for ``function``'s parameters (``add_function_arguments``), with
    ``--config`` / ``--print_config``; ``positional`` (a list parameter) takes the positional
    arguments (``nargs``), ``as_positional`` makes the parameters without a default positional;
    ``bool`` parameters are flags (``--name`` / ``--no_name``)."""
    description, helps = _docs(function)
    parser = OmgArgumentParser(prog=prog, description=description, exit_on_error=False)
    parser.add_argument("--config", action=ActionConfigFile,
                        help="a YAML file of any of the options below (options after it override it)")
    params = inspect.signature(function).parameters
    hints = typing.get_type_hints(function)
    if positional is not None:
        hint = hints[positional]  # list[X] or list[X] | None
        if typing.get_origin(hint) in (typing.Union, types.UnionType):
            hint = next(a for a in typing.get_args(hint) if a is not type(None))
        item = (typing.get_args(hint) or (str,))[0]
        # no values leave the key alone (SUPPRESS), so that a --config file can give them
        default = {"default": argparse.SUPPRESS} if nargs in ("*", "?") else {}
        parser.add_argument(positional, nargs=nargs, type=item, help=helps.get(positional), **default)
    flags = [name for name in params if hints.get(name) is bool]
    skip = {*flags, *([positional] if positional else []), *([RECORDED] if RECORDED in params else [])}
    parser.add_function_arguments(function, as_group=False, as_positional=as_positional, skip=skip)
    for name in flags:
        parser.add_argument(f"--{name}", action=ActionYesNo, default=params[name].default, help=helps.get(name))
    return parser


def parse(parser: ArgumentParser, argv: list[str], help_prog: str | None = None) -> Namespace:
    """``argv`` parsed; bad input a one-line UsageError."""
    check_config_files(argv)
    try:
        return parser.parse_args(argv)
    except argparse.ArgumentError as e:
        raise UsageError(explain(e, hint=f"see `{help_prog or parser.prog} --help`")) from None


def call(function: Callable, config: Namespace, command: str):
    """``function`` called with the parsed values of its parameters (and the command line)."""
    params = inspect.signature(function).parameters
    kwargs = {name: config[name] for name in params if name in config}
    if RECORDED in params:
        kwargs[RECORDED] = command
    return function(**kwargs)


def run(function: Callable, argv: list[str], prog: str, **kwargs):
    """``prog ARGV``: parse ``argv`` for ``function`` (``function_parser``'s ``kwargs``) and call it."""
    parser = function_parser(function, prog, **kwargs)
    return call(function, parse(parser, argv), " ".join([prog, shlex.join(argv)]).strip())


def run_subcommands(prog: str, description: str, commands: dict[str, tuple[Callable, dict]], argv: list[str]):
    """``prog NAME ARGV``: one typed function per subcommand (``commands``: name -> (function,
    ``function_parser`` keyword arguments)), as jsonargparse subcommands."""
    parser = OmgArgumentParser(prog=prog, description=description, exit_on_error=False)
    subcommands = parser.add_subcommands(dest="subcommand")
    for name, (function, kwargs) in commands.items():
        subparser = function_parser(function, f"{prog} {name}", **kwargs)
        subcommands.add_subcommand(name, subparser, help=_docs(function)[0].split("\n")[0])
    if not argv:
        parser.print_help()
        return None
    config = parse(parser, argv, help_prog=f"{prog} {argv[0]}" if argv[0] in commands else prog)
    name = config.subcommand
    return call(commands[name][0], config[name], " ".join([prog, shlex.join(argv)]))
