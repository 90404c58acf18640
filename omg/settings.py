"""Typed settings groups: the nested mappings of a module's settings (``dit``, ``moc``, ``config``, ...)
as frozen dataclasses, so that ``omg fit --help`` and ``--print_config`` show and check each key.

A group of *overrides* (``overrides``) has every field of the config it overrides (``DiTConfig``,
``MoCConfig``, ...) with the same type, defaulting to None: "the flavor's (or the config's) value".
Only the fields a run sets are passed on, so a run that sets none builds what it built before the
groups were typed, and a checkpoint keeps the mapping it always kept (``settings_dict``: the set
fields, plain types, as checkpoints load weights-only). ``settings`` reads a group from what
constructors are given: the dataclass (``omg fit``), a mapping (a checkpoint's hyper-parameters, a
Python caller) or None, an unknown key being one line that names it and the accepted ones.

A group of *values* (a module's ``optim``, its ``loss`` weights) has a value in every field, the family's
defaults: ``group`` reads one from the same inputs, a mapping setting some fields over the default's, and
``regroup`` moves the older flat keys of its fields (``lr``, ``vel_weight``) into it, as checkpoints and
configs written before the groups hold them.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import typing
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

from omg.errors import UsageError

T = TypeVar("T")


def overrides(config: type, name: str, module: str, doc: str, exclude: tuple[str, ...] = ("name",)) -> type:
    """A frozen dataclass ``name`` with each field of the dataclass ``config`` (but ``exclude``) typed as
    there or None, default None. Its docstring ``doc``; ``module`` (the caller's ``__name__``) is where
    it is importable from, for jsonargparse's ``--help`` and ``--print_config``."""
    hints = typing.get_type_hints(config)
    return _unset_group(name, module, doc, [(f.name, hints[f.name]) for f in dataclasses.fields(config)
                                            if f.name not in exclude])


def arguments(function: Any, name: str, module: str, doc: str) -> type:
    """A frozen dataclass ``name`` with each keyword argument of ``function`` (a class: its ``__init__``) typed
    as there or None, default None (unset: the argument's default), as ``overrides`` does for a dataclass."""
    init = function.__init__ if isinstance(function, type) else function
    hints = typing.get_type_hints(init)
    keywords = [p.name for p in inspect.signature(init).parameters.values()
                if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    return _unset_group(name, module, doc, [(keyword, hints[keyword]) for keyword in keywords])


def _unset_group(name: str, module: str, doc: str, typed: list[tuple[str, Any]]) -> type:
    """The frozen dataclass of ``typed`` (field, type) pairs, each ``type | None`` with default None."""
    cls = dataclasses.make_dataclass(name, [(field, hint | None, dataclasses.field(default=None))
                                            for field, hint in typed], frozen=True)
    cls.__module__, cls.__doc__ = module, doc
    return cls


def settings(cls: type[T], value: Any, key: str) -> T:
    """``value`` (None, a ``cls`` or a mapping of its fields) as a ``cls``; UsageError naming ``key``
    (``model.init_args.dit``) for an unknown field or a value of another kind."""
    return value if isinstance(value, cls) else cls(**_fields_of(cls, value, key))


def _fields_of(cls: type, value: Any, key: str) -> dict[str, Any]:
    """The fields ``value`` (None, a dataclass or a mapping) gives a ``cls``; one line naming ``key`` for an unknown
    field or a value of another kind."""
    if value is None:
        return {}
    accepted = [f.name for f in dataclasses.fields(cls)]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = settings_dict(value)
    if not isinstance(value, Mapping):
        raise UsageError(f"{key} must be a mapping of {', '.join(accepted)}; got {type(value).__name__} {value!r}")
    if unknown := [k for k in value if k not in accepted]:
        raise UsageError(unknown_key_line(key, key, unknown[0], accepted))
    return dict(value)


def unknown_key_line(where: str, group: str, field: str, accepted: list[str]) -> str:
    """The one line, headed ``where``, for ``field``, no key of the group ``group`` (``model.init_args.loss``)
    whose keys are ``accepted``: it names them, and the closest first where one is near (``vel``: ``vel_weight``)."""
    near = closest(field, accepted)
    if near is None:
        return f"{where}: unknown key {field!r}; accepted keys: {', '.join(accepted)}"
    return f"{where}: unknown key {field!r}; did you mean {group}.{near}? (accepted keys: {', '.join(accepted)})"


def closest(name: str, candidates: Iterable[str]) -> str | None:
    """The candidate nearest ``name``, None where none is near. Of those that begin with ``name`` (what argparse
    would take an abbreviation for) the nearest; else the nearest of all whose similarity (difflib's ratio) is
    0.6 at least, which a misspelling reaches and an unrelated word does not."""
    candidates = sorted(set(candidates))
    extending = [c for c in candidates if c.startswith(name)]
    found = difflib.get_close_matches(name, extending or candidates, n=1, cutoff=0.0 if extending else 0.6)
    return found[0] if found else None


def group(default: T, value: Any, key: str) -> T:
    """``value`` as a group of ``default``'s class: None is ``default``, a mapping sets some of its fields (the
    others ``default``'s: a family's own defaults, as ``--model.init_args.optim.lr`` keeps the rest); an unknown
    key is one line naming ``key`` and the accepted ones. For the groups whose fields all have values (``optim``,
    ``loss``), where ``settings`` reads those whose unset fields are None."""
    if value is None or isinstance(value, type(default)):
        return default if value is None else value
    return dataclasses.replace(default, **_fields_of(type(default), value, key))


def regroup(values: Mapping[str, Any], fields: Mapping[str, str],
            key: str = "model.init_args") -> tuple[dict[str, Any], list[tuple[str, str]]]:
    """``values`` with each key that ``fields`` (flat key -> its group) names moved into its group's mapping
    (``{lr: 1e-3}`` -> ``{optim: {lr: 1e-3}}``): the flat keys of settings that are grouped now, as older
    checkpoints and configs hold them; also the (key, group) pairs moved. A field given both ways is one line
    naming both (``key``: where ``values`` sit); a group that is no mapping is left to the caller's check."""
    out, moved = dict(values), []
    for flat in [k for k in values if k in fields and k not in fields.values()]:
        name = fields[flat]
        given = out.get(name)
        if dataclasses.is_dataclass(given) and not isinstance(given, type):
            given = settings_dict(given)
        if given is not None and not isinstance(given, Mapping):
            continue
        if flat in (given or {}):
            raise UsageError(f"{key}.{flat} and {key}.{name}.{flat} are both set: keep {key}.{name}.{flat} only "
                             f"({key}.{flat} is its older name)")
        out[name] = {**(given or {}), flat: out.pop(flat)}
        moved.append((flat, name))
    return out, moved


def set_fields(cls: type, value: Any, key: str) -> dict[str, Any]:
    """The fields ``value`` (as ``settings`` reads it) sets, as plain types: the keyword arguments for the
    config or callable the group overrides, and what checkpoints keep."""
    return settings_dict(settings(cls, value, key))


def settings_dict(group: Any) -> dict[str, Any]:
    """The fields a group sets (not None), as plain types: what checkpoints and hparams.yaml keep."""
    return {f.name: _plain(getattr(group, f.name)) for f in dataclasses.fields(group)
            if getattr(group, f.name) is not None}


def check_range(key: str, value: Any, ok: bool, wanted: str) -> None:
    """One line naming ``key`` unless ``ok``: ``key must be {wanted}, got {value!r}``."""
    if not ok:
        raise UsageError(f"{key} must be {wanted}, got {value!r}")


def _plain(value: Any) -> Any:
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


__all__ = ["arguments", "check_range", "closest", "group", "overrides", "regroup", "set_fields", "settings",
           "settings_dict", "unknown_key_line"]
