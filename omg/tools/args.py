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

Bad input is one line, ``<key>: <reason>``. Only jsonargparse's public API is used: a parse that
fails raises ``ArgumentError`` (``exit_on_error=False``); ``locate`` then checks each setting the
user gave on its own against its key's type (``Settings``, from the function's signature) with a
one-option parser, and ``explain`` builds the line from the setting that fails alone (its key,
type and value), from a ``UsageError`` a component raised, or from the innermost exception of the
chain: never from the text of jsonargparse's nested messages.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import shlex
import types
import typing
from pathlib import Path, PurePath
from typing import Any, Callable, Iterable

from jsonargparse import ActionConfigFile, ActionYesNo, ArgumentParser, Namespace
from jsonargparse.typing import ClosedUnitInterval, NonNegativeInt, PositiveInt, restricted_number_type

from omg.errors import UsageError
from omg.files import read_text
from omg.settings import closest

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
# jsonargparse registers one type per set of restrictions: every ">= 0, finite" option is a time span
NonNegativeSeconds = number_type("NonNegativeSeconds", float, [(">=", 0.0), ("<", math.inf)],
                                 "a number of seconds >= 0")
Fraction = number_type("Fraction", float, [(">=", 0.0), ("<", 1.0)], "a number in [0, 1)")
WANTED[ClosedUnitInterval] = "a number in [0, 1]"  # jsonargparse's

__all__ = ["ClosedUnitInterval", "FiniteFloat", "Fraction", "NonNegativeSeconds", "NonNegativeInt",
           "PositiveFiniteFloat", "PositiveInt",
           "Seed", "number_type", "function_parser", "run", "run_subcommands", "explain", "Settings", "locate",
           "check_config_files", "underscore_options", "repeated", "ExactOptions"]


# -- errors -----------------------------------------------------------------------------------
# jsonargparse raises one ArgumentError for bad input, its text nested (a union's every member, a
# class's every candidate). The key at fault is found again with public calls only: each setting
# the user gave (``--key VALUE`` on the command line, ``key: value`` in a ``--config`` file) is
# checked on its own against its key's type, by a one-option jsonargparse parser; the first that
# fails alone is the one to name. ``Settings`` knows the keys' types: the tools' from their
# functions' signatures (``function_parser``), ``omg fit``'s from the classes it configures
# (``omg.tools.lightning``).


class Settings:
    """The keys a parser takes and their types: ``types`` (key -> type hint), ``flags`` (options
    that take no value, ``--preview`` / ``--no_preview``), ``options`` (every long option, for
    ``underscore_options`` and ``unknown_option``)."""

    def __init__(self, types: dict[str, Any] | None = None, flags: set[str] | None = None,
                 options: set[str] | None = None):
        self.types = dict(types or {})
        self.flags = set(flags or ())
        self.options = set(options or ()) | {f"--{key}" for key in self.types} | self.flags
        self.known: set[str] | None = None  # the options an unknown option is told from; None: ``options``

    def type_of(self, key: str, given: list[tuple[str, Any, bool]], value: Any = None) -> Any:
        """The type hint to check ``value`` of ``key`` against (``given``: all the user's settings,
        for types that depend on another setting, such as a model's class); None where unknown."""
        return self.types.get(key)

    def name_of(self, key: str) -> str:
        """How an error names ``key`` (as the user spelled it, unless a parser spells it otherwise)."""
        return key

    def unknown_key(self, key: str, given: list[tuple[str, Any, bool]]) -> str | None:
        """The error line for a ``key`` this parser does not take where it can tell (a typed settings
        group's unknown field); None otherwise."""
        return None

    def unknown_option(self, key: str, given: list[tuple[str, Any, bool]]) -> str | None:
        """The error line for an option ``--key`` of the command line that is none of ``options`` (nor extends one,
        ``--trainer.logger.init_args.name`` extending ``--trainer.logger``) and has a near one: it names both
        (``--num_samp``: ``--num_samples``, which argparse would have taken it for). None otherwise: jsonargparse's
        own message says the rest."""
        known = {option[2:] for option in (self.options if self.known is None else self.known)
                 if option.startswith("--")}
        key = key.removesuffix("+")  # jsonargparse's ``--list+=ITEM``
        if not known or key in known or key == "help" or key.endswith(".help"):
            return None
        if any(key.startswith(f"{option}.") for option in known):
            return None
        return unknown_option_line(self.name_of(key), nearest_key(key, known))


def nearest_key(key: str, known: Iterable[str]) -> str | None:
    """The key of ``known`` nearest the dotted ``key``, among those under the same parent (``trainer.max_st``:
    the ``trainer.*`` keys, by their last part) where there are any: a shared parent is no likeness."""
    parent, _, leaf = key.rpartition(".")
    siblings = {k.rpartition(".")[2]: k for k in known if k.rpartition(".")[0] == parent}
    if not siblings:
        return closest(key, known)
    near = closest(leaf, siblings)
    return siblings[near] if near is not None else None


def unknown_option_line(key: str, near: str | None) -> str | None:
    """``--key: unknown option; did you mean --near?`` (None without a near option)."""
    if near is None:
        return None
    return f"--{key}: unknown option (options are never abbreviated); did you mean --{near}?"


def _config_settings(text_or_path: str, loader: Callable[[str], Any]) -> list[tuple[str, Any, bool]]:
    """``(key, value, False)`` of every key of a ``--config`` (a file, or a mapping given inline),
    nested keys dotted, outer keys before inner ones."""
    try:
        path = Path(text_or_path)
        value = loader(read_text(text_or_path, "--config") if path.is_file() else text_or_path)
    except Exception:  # noqa: BLE001 - jsonargparse reports a config it cannot read
        return []
    pairs: list[tuple[str, Any, bool]] = []

    def walk(mapping: dict, prefix: str) -> None:
        for key, item in mapping.items():
            pairs.append((f"{prefix}{key}", item, False))
            if isinstance(item, dict):
                walk(item, f"{prefix}{key}.")

    if isinstance(value, dict):
        walk(value, "")
    return pairs


def given_settings(argv: list[str], settings: Settings) -> list[tuple[str, Any, bool]]:
    """``(key, value, from_command_line)`` of every setting in ``argv``, in its order, a
    ``--config``'s keys at its place; positionals and flags are left out (they have no value to
    check)."""
    try:
        from jsonargparse import get_loader

        loader = get_loader("yaml")
    except (ImportError, ValueError):  # pragma: no cover - a jsonargparse without get_loader
        import yaml

        loader = yaml.safe_load
    pairs: list[tuple[str, Any, bool]] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        i += 1
        if arg == "--":
            break
        if not arg.startswith("-") or arg in settings.flags or arg in ("-h", "--help", "--print_config"):
            continue
        name, sep, value = arg.partition("=")
        if not sep:
            if i == len(argv):
                break
            value, i = argv[i], i + 1
        if name in ("--config", "-c"):
            pairs += _config_settings(value, loader)
        elif name.startswith("--"):
            pairs.append((name[2:], value, True))
    return pairs


def check_alone(hint: Any, value: Any, from_command_line: bool) -> BaseException | None:
    """The error jsonargparse raises for ``value`` as a ``hint`` (given on the command line or in a
    config file), on a parser of that one option; None when it passes (or the type cannot stand
    alone)."""
    from jsonargparse import ArgumentError

    try:
        parser = ArgumentParser(exit_on_error=False)
        parser.add_argument("--value", type=hint)
    except Exception:  # noqa: BLE001 - a type jsonargparse takes only in its context
        return None
    try:
        if from_command_line:
            parser.parse_args([f"--value={value}"])
        else:
            parser.parse_object({"value": value})
    except (ArgumentError, TypeError, ValueError) as e:
        return e
    except Exception:  # noqa: BLE001 - not a type error: not this key's fault
        return None
    return None


def locate(argv: list[str], settings: Settings) -> tuple[str, Any, Any, BaseException] | None:
    """``(key, type hint, value, error)`` of the first setting in ``argv`` that fails its type on
    its own; None when each passes alone (the error is another one: an unknown key, a missing
    argument, a value that fails only with the others)."""
    given = given_settings(argv, settings)
    for key, value, from_command_line in given:  # first: an option no parser takes, spelled in part or misspelt
        if from_command_line and (unknown := settings.unknown_option(key, given)) is not None:
            return settings.name_of(key), None, value, UsageError(unknown)
    for key, value, _ in given:  # then: an unknown key inside a mapping fails the mapping's type too
        if (unknown := settings.unknown_key(key, given)) is not None:
            return settings.name_of(key), None, value, UsageError(unknown)
    for key, value, from_command_line in given:
        hint = settings.type_of(key, given, value)
        if hint is None:
            continue
        error = check_alone(hint, value, from_command_line)
        if error is not None:
            return settings.name_of(key), hint, value, error
    return None


# -- option spellings ----------------------------------------------------------------------------
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


class ExactOptions:
    """A parser that takes each option only as spelled in full. argparse takes an unambiguous prefix of a long
    option for it (``allow_abbrev``), so that ``--model.init_args.loss.vel 3`` would set ``loss.vel_weight`` without
    a word; here it is an unknown option (``Settings.unknown_option`` names the one meant). jsonargparse builds the
    parsers of a class's arguments (``--model.init_args.*``) and of subcommands as ``type(parser)``, so every
    parser below a parser of this class is one too."""

    def __init__(self, *args: Any, **kwargs: Any):
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)


class OmgArgumentParser(ExactOptions, ArgumentParser):
    """The tools' jsonargparse parser; ``function_parser`` gives it its ``settings``."""

    settings: Settings = Settings()


def _chain(error: BaseException) -> list[BaseException]:
    """``error`` and what caused it, outermost first."""
    chain: list[BaseException] = []
    while error is not None and all(error is not e for e in chain):
        chain.append(error)
        error = error.__cause__ or (None if error.__suppress_context__ else error.__context__)
    return chain


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


def explain(error: BaseException, hint: str = "", where: tuple[str, Any, Any, BaseException] | None = None) -> str:
    """One line for a parsing error: ``<key>: <reason>``.

    A UsageError in the chain (a component refusing its value) is the reason as it is. Otherwise
    ``where`` (``locate``: the setting that fails on its own) gives the key, and its type and value
    the reason (``expected an integer >= 1, got '-2'``); for types without a wording, the first
    line of the innermost exception of that setting's check. Without ``where``, the innermost
    exception's first line, and ``hint`` after it (unrecognized arguments, unknown config keys,
    missing arguments)."""
    chain = _chain(error)
    usage = next((e for e in chain if isinstance(e, UsageError)), None)
    if usage is not None:
        return str(usage)
    if where is not None:
        key, type_hint, value, check_error = where
        usage = next((e for e in _chain(check_error) if isinstance(e, UsageError)), None)
        if usage is not None:
            return str(usage)
        wanted = describe(type_hint)
        if wanted and isinstance(value, (str, int, float, bool, list, dict, PurePath, type(None))):
            return f"{key}: expected {wanted}, got {value!r}"
        return f"{key}: {_first_line(_chain(check_error)[-1])}"
    reason = _first_line(chain[-1])
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
    ``bool`` parameters are flags (``--name`` / ``--no_name``). Its ``settings`` hold the types of
    the options, from the signature."""
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
    added = parser.add_function_arguments(function, as_group=False, as_positional=as_positional, skip=skip)
    flag_options: set[str] = set()
    for name in flags:
        action = parser.add_argument(f"--{name}", action=ActionYesNo, default=params[name].default,
                                     help=helps.get(name))
        flag_options.update(action.option_strings)
    typed = {}
    for key in added or []:
        if key in hints and key in params:
            hint = hints[key]
            typed[key] = typing.Optional[hint] if params[key].default is None and hint is not Any else hint
    parser.settings = Settings(typed, flag_options, {"--config", "--print_config"})
    return parser


def parse(parser: ArgumentParser, argv: list[str], help_prog: str | None = None,
          settings: Settings | None = None) -> Namespace:
    """``argv`` parsed; bad input a one-line UsageError (``explain``; ``settings``: the parser's,
    by default its ``settings`` attribute)."""
    from jsonargparse import ArgumentError

    settings = settings or getattr(parser, "settings", None) or Settings()
    check_config_files(argv)
    argv = lone_items_listed(underscore_options(argv, settings.options), settings.types)
    try:
        return parser.parse_args(argv)
    except (ArgumentError, argparse.ArgumentError) as e:
        where = locate(argv, settings)
        raise UsageError(explain(e, hint=f"see `{help_prog or parser.prog} --help`", where=where)) from None


def _takes_a_list(hint: Any) -> bool:
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return any(_takes_a_list(a) for a in typing.get_args(hint))
    return typing.get_origin(hint) in (list, tuple)


def lone_items_listed(argv: list[str], types_: dict[str, Any]) -> list[str]:
    """``argv`` with a list option given one plain value (``--configs a.yaml``, ``--batch_sizes 8``) as the
    one-item list ``[a.yaml]`` jsonargparse takes; a value that is already a list, or holds what a list
    would read differently (``,[]{}:#`` or quotes), is left for the parser to judge."""
    listed = {f"--{key}" for key, hint in types_.items() if _takes_a_list(hint)}
    out = list(argv)
    for i, arg in enumerate(out):
        flag, sep, value = arg.partition("=")
        if flag not in listed:
            continue
        at = i if sep else i + 1
        value = value if sep else (out[at] if at < len(out) else "")
        if value and not value.startswith("-") and not set(value) & set(",[]{}:#'\"") and not value.isspace():
            out[at] = f"{flag}=[{value}]" if sep else f"[{value}]"
    return out


def call(function: Callable, config: Namespace, command: str):
    """``function`` called with the parsed values of its parameters (and the command line)."""
    params = inspect.signature(function).parameters
    kwargs = {name: config[name] for name in params if name in config}
    if RECORDED in params:
        kwargs[RECORDED] = command
    return function(**kwargs)


def repeated(argv: list[str], flag: str) -> list[str]:
    """``argv`` with a repeated list option (``--ckpt A --ckpt B``) as jsonargparse's list ``--ckpt [A, B]`` (it
    would keep only the last)."""
    values, rest, i = [], [], 0
    while i < len(argv):
        if argv[i] == flag and i + 1 < len(argv):
            values.append(argv[i + 1])
            i += 2
        elif argv[i].startswith(flag + "="):
            values.append(argv[i].split("=", 1)[1])
            i += 1
        else:
            rest.append(argv[i])
            i += 1
    if not values:
        return rest
    joined = values[0] if len(values) == 1 and values[0].lstrip().startswith("[") else json.dumps(values)
    return [flag, joined, *rest]


def run(function: Callable, argv: list[str], prog: str, **kwargs):
    """``prog ARGV``: parse ``argv`` for ``function`` (``function_parser``'s ``kwargs``) and call it."""
    parser = function_parser(function, prog, **kwargs)
    return call(function, parse(parser, argv), " ".join([prog, shlex.join(argv)]).strip())


def run_subcommands(prog: str, description: str, commands: dict[str, tuple[Callable, dict]], argv: list[str]):
    """``prog NAME ARGV``: one typed function per subcommand (``commands``: name -> (function,
    ``function_parser`` keyword arguments)), as jsonargparse subcommands. Only NAME's parser is built when
    ARGV starts with a known NAME (each parser reads its function's signature and docstring); every one of
    them for the command list, ``--help`` or an unknown name."""
    parser = OmgArgumentParser(prog=prog, description=description, exit_on_error=False)
    subcommands = parser.add_subcommands(dest="subcommand")
    named = argv[0] if argv and argv[0] in commands else None
    subparsers = {}
    for name, (function, kwargs) in commands.items():
        if named in (None, name):
            subparsers[name] = function_parser(function, f"{prog} {name}", **kwargs)
            subcommands.add_subcommand(name, subparsers[name], help=_docs(function)[0].split("\n")[0])
    if not argv:
        parser.print_help()
        return None
    # the options of the subcommands built are spelled with underscores (as jsonargparse nests them)
    # and the keys of the one given are checked alone, without its name
    options = set().union(*(p.settings.options for p in subparsers.values()))
    chosen = subparsers.get(argv[0])
    settings = Settings(chosen.settings.types, chosen.settings.flags) if chosen else Settings()
    settings.options = options
    if chosen is not None:  # what an unknown option is checked against: the chosen command's own
        settings.known = chosen.settings.options
    config = parse(parser, argv, help_prog=f"{prog} {argv[0]}" if chosen else prog, settings=settings)
    name = config.subcommand
    return call(commands[name][0], config[name], " ".join([prog, shlex.join(argv)]))
