"""``omg shards build|synth|inspect``."""

from __future__ import annotations

import argparse
from collections import Counter
import hashlib
import inspect
import math
import shlex
import sys
import types
import typing
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import yaml

from omg.cli import (ToolParser, check_output_dir, nonneg_float, nonneg_int, positive_float, positive_int,
                     read_text, removing_created, seed_int)
from omg.data.shards import ShardWriter, check_shards
from omg.errors import UsageError
from omg.motion import Clip, get_representation
from omg.registry import DATA_SOURCES
from omg.skeleton import get_skeleton

MAX_FPS = 1000.0

# What `omg shards synth` builds by default: the embedded mini data in shards/mini.
# (subdirectory, skeleton, representation, clips)
MINI_SETS = (
    ("human263", "smpl22", "humanml3d263", 100),
    ("animal_maa", "smal35", "maa", 56),
)


def in_val_split(clip_id: str, val_fraction: float) -> bool:
    """A stable split: the same id lands in the same split whatever else is in the set."""
    h = int.from_bytes(hashlib.sha1(clip_id.encode()).digest()[:8], "big") / 2**64
    return h < val_fraction


def in_val_labels(clip: Clip, val_where: dict[str, list[str]]) -> bool:
    """A split by take: the clip's labels match every ``key: [values]`` of ``val_where``."""
    return all(str(clip.labels.get(key)) in values for key, values in val_where.items())


def _split(items: Iterable[Clip | Exception | None], want_val: bool, val_fraction: float,
           val_where: dict[str, list[str]] | None) -> Iterator[Clip | Exception | None]:
    for item in items:
        if isinstance(item, Clip):
            in_val = in_val_labels(item, val_where) if val_where else in_val_split(item.id, val_fraction)
            yield item if in_val == want_val else None
        else:  # a failed item is counted once, in the training split
            yield None if want_val or item is None else item


def shuffled(items: Iterable, buffer: int, seed: int) -> Iterator:
    """The source's items in a seeded random order, through a buffer of ``buffer`` items (0: as
    they come). Sources list their files in name order, which puts long runs of one action into
    one shard; the training stream's shuffle buffer then sees few actions per batch. The order
    is a function of the source's order and the seed, so an interrupted build resumes."""
    if buffer <= 1:
        yield from items
        return
    rng, pool = np.random.default_rng(seed), []
    for item in items:
        pool.append(item)
        if len(pool) >= buffer:
            i = int(rng.integers(len(pool)))
            pool[i], pool[-1] = pool[-1], pool[i]
            yield pool.pop()
    order = rng.permutation(len(pool))
    yield from (pool[i] for i in order)


def build(
    source: str,
    out: str | Path,
    representation: str,
    skeleton: str,
    fps: float,
    input: str | None = None,
    val_fraction: float = 0.0,
    max_clips: int = 1000,
    max_mb: float = 256.0,
    options: dict | None = None,
    command: str = "",
    log=lambda message: None,
    val_where: dict[str, list[str]] | None = None,
    shuffle_buffer: int = 0,
    seed: int = 0,
) -> list:
    """Build a shard set (``out``, or ``out/train`` and ``out/val`` with a validation split).

    Every argument is checked before a folder is made; a build that fails removes the folders
    it created (an existing ``out`` stays, and with it the shards an interrupted build finished)."""
    if not _is_number(fps) or not 0 < fps <= MAX_FPS:
        raise UsageError(f"--fps must be a number in (0, {MAX_FPS:g}], got {fps!r}")
    if not _is_number(val_fraction) or not 0.0 <= val_fraction < 1.0:
        raise UsageError(f"--val-fraction must be in [0, 1), got {val_fraction!r}")
    if not _is_number(max_clips) or isinstance(max_clips, float) or max_clips < 1:
        raise UsageError(f"--max-clips must be a positive integer, got {max_clips!r}")
    if not _is_number(max_mb) or max_mb * 2**20 < 1:
        raise UsageError(f"--max-mb must be a positive number of megabytes (at least 1 byte), got {max_mb!r}")
    open_source = DATA_SOURCES.get(source)
    options = _check_options(source, open_source, options or {})
    rep = get_representation(representation, get_skeleton(skeleton))
    out = check_output_dir(out)
    if not _is_number(shuffle_buffer) or isinstance(shuffle_buffer, float) or shuffle_buffer < 0:
        raise UsageError(f"--shuffle-buffer must be an integer >= 0, got {shuffle_buffer!r}")
    if val_where and val_fraction > 0:
        raise UsageError("give --val-fraction (a random split) or --val-where (a split by label), not both")
    splits = {"train": False, "val": True} if val_fraction > 0 or val_where else {"": False}
    summaries = []
    try:
        with removing_created(*(out / name for name in splits)):
            for name, want_val in splits.items():
                items = open_source(input=input, skeleton=rep.skeleton, fps=fps, **options)
                stats = getattr(items, "stats", {}).get(rep.name)  # a source's published normalisation (SourceItems)
                items = shuffled(items, shuffle_buffer, seed)
                if name:
                    items = _split(items, want_val, val_fraction, val_where)
                writer = ShardWriter(out / name, rep, fps, max_clips, int(max_mb * 2**20), command, log=log,
                                     stats=stats)
                summaries.append(writer.write(items))
    except UnicodeDecodeError as e:  # a text file an option names (a YAML joint map, ...) in another encoding
        named = [f"--option {k}={v}" for k, v in options.items() if isinstance(v, str) and not _is_utf8_file(v)]
        which = f"{named[0]}: not a UTF-8 text file" if named else "a file is not UTF-8 text"
        raise UsageError(f"{which} ({e.reason} at offset {e.start}); save it as UTF-8") from None
    return summaries


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_utf8_file(path: str) -> bool:
    try:
        Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return False
    except (OSError, ValueError):
        return True  # not a readable file: not the one
    return True


RESERVED_OPTIONS = {"input": "--input", "skeleton": "--skeleton", "fps": "--fps"}
_KINDS = {int: "an integer", float: "a number", str: "a string", bool: "true or false", list: "a list",
          dict: "a mapping", type(None): "null"}


def _check_options(name: str, source, options: dict) -> dict:
    """``--option`` keys against the source's parameters, values against their annotations.

    Numbers must be finite and >= 0: source options that are numbers count clips or frames, or
    are seeds and sizes."""
    try:
        params = inspect.signature(source).parameters
    except (TypeError, ValueError):  # not introspectable: the source checks its own options
        params = {}
    try:
        hints = typing.get_type_hints(source)
    except Exception:  # an annotation that does not resolve: no type check
        hints = {}
    open_ended = not params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    known = [k for k, p in params.items() if k not in RESERVED_OPTIONS and p.kind is not inspect.Parameter.VAR_KEYWORD]
    for key, value in options.items():
        if not isinstance(key, str) or not key.isidentifier():
            raise UsageError(f"--option {key}={value}: the key must be a name such as num_clips")
        if key in RESERVED_OPTIONS:
            raise UsageError(f"--option {key}=...: give it as {RESERVED_OPTIONS[key]}")
        if key not in params and not open_ended:
            raise UsageError(f"--option {key}: the {name} source has no such option; "
                             f"its options: {', '.join(known) or 'none'}")
        if isinstance(value, (int, float)) and not isinstance(value, bool) and not (math.isfinite(value) and value >= 0):
            raise UsageError(f"--option {key}={value}: expected a finite number >= 0")
        allowed = _allowed_types(hints.get(key))
        if allowed and not _fits(value, allowed):
            kinds = " or ".join(dict.fromkeys(_KINDS[t] for t in allowed))
            raise UsageError(f"--option {key}={value!r}: the {name} source expects {kinds}")
    return options


def _allowed_types(hint) -> tuple[type, ...] | None:
    """The plain types a parameter annotation admits, or None when it is not that simple."""
    if hint is None or hint is typing.Any:
        return None
    args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    plain = tuple(typing.get_origin(a) or a for a in args)
    if any(t not in _KINDS for t in plain):
        return None
    return plain


def _fits(value, allowed: tuple[type, ...]) -> bool:
    if isinstance(value, bool):
        return bool in allowed
    if isinstance(value, int) and (int in allowed or float in allowed):
        return True
    return isinstance(value, tuple(t for t in allowed if t is not int))


def _parse_options(pairs: list[str]) -> dict:
    options = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--option {pair!r} must look like key=value")
        try:
            options[key.strip().replace("-", "_")] = yaml.safe_load(value)
        except yaml.YAMLError as e:
            raise UsageError(f"--option {pair!r}: the value is not valid YAML ({str(e).splitlines()[0]})") from None
    return options


def _config_value(config: str, key: str, action: argparse.Action, value):
    """A value of ``omg shards build --config FILE`` checked as its command-line flag would be."""
    if action.dest == "option":
        if value is None:
            return []
        if isinstance(value, dict):
            return value
        if isinstance(value, list) and all(isinstance(v, str) for v in value):
            return _parse_options(value)
        raise UsageError(f"{config}: {key!r} must be a mapping of source options, got {value!r}")
    if action.dest == "val_where":
        if isinstance(value, dict) and all(isinstance(v, (str, list)) for v in value.values()):
            return _parse_val_where([f"{k}={v if isinstance(v, str) else ','.join(map(str, v))}" for k, v in value.items()])
        raise UsageError(f"{config}: {key!r} must map labels to values, e.g. {{style: [old, proud]}}, got {value!r}")
    if value is None:
        return None
    if action.type is None:
        if not isinstance(value, str):
            raise UsageError(f"{config}: {key!r} must be a string, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise UsageError(f"{config}: {key!r} must be a number, got {value!r}")
    try:
        return action.type(str(value))
    except (argparse.ArgumentTypeError, TypeError, ValueError) as e:
        reason = str(e) if isinstance(e, argparse.ArgumentTypeError) else f"invalid value {value!r}"
        raise UsageError(f"{config}: {key!r}: {reason}") from None


def _build_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards build", description="Import motion from a registered data source into shards.")
    p.add_argument("--config", help="YAML file with any of the options below (command-line values win)")
    p.add_argument("--source", help=f"data source name ({', '.join(DATA_SOURCES.names())})")
    p.add_argument("--input", help="the source's input (a directory or file), if it takes one")
    p.add_argument("--out", help="output directory")
    p.add_argument("--representation", default="humanml3d263")
    p.add_argument("--skeleton", default="smpl22")
    p.add_argument("--fps", type=positive_float, default=30.0, help=f"frames per second, at most {MAX_FPS:g}")
    p.add_argument("--val-fraction", type=nonneg_float, default=0.0, help="put this share of clips in out/val, the rest in out/train")
    p.add_argument("--max-clips", type=positive_int, default=1000, help="clips per shard at most")
    p.add_argument("--max-mb", type=positive_float, default=256.0, help="megabytes per shard at most")
    p.add_argument("--val-where", action="append", default=[], metavar="LABEL=V1,V2",
                   help="put the clips whose label LABEL is one of the values in out/val (a split by take; repeatable: all must match)")
    p.add_argument("--shuffle-buffer", type=nonneg_int, default=1000,
                   help="write clips in a seeded random order through a buffer of this many clips (0: input order)")
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the clip order")
    p.add_argument("--option", action="append", default=[], help="key=value passed to the source (repeatable)")
    args = p.parse_args(argv)
    if args.config:
        try:
            config = yaml.safe_load(read_text(args.config, "--config"))
        except yaml.YAMLError as e:
            raise UsageError(f"--config {args.config}: not valid YAML ({str(e).splitlines()[0]})") from None
        if not isinstance(config, dict):
            raise UsageError(f"--config {args.config}: not a YAML mapping file")
        actions = {a.dest: a for a in p._actions if a.dest not in ("help", "config")}
        for key, value in config.items():
            dest = str(key).replace("-", "_")
            if dest not in actions:
                raise UsageError(f"{args.config}: unknown key {key!r}; known keys: {', '.join(sorted(actions))}")
            if getattr(args, dest) == p.get_default(dest):
                setattr(args, dest, _config_value(args.config, key, actions[dest], value))
    for required in ("source", "out"):
        if not getattr(args, required):
            raise UsageError(f"omg shards build: --{required} is required")
    options = args.option if isinstance(args.option, dict) else _parse_options(args.option)
    command = "omg shards build " + shlex.join(argv)
    val_where = args.val_where if isinstance(args.val_where, dict) else _parse_val_where(args.val_where)
    for summary in build(args.source, args.out, args.representation, args.skeleton, args.fps, args.input,
                         args.val_fraction, args.max_clips, args.max_mb, options, command, log=print,
                         val_where=val_where, shuffle_buffer=args.shuffle_buffer, seed=args.seed):
        print(summary)


def _parse_val_where(pairs: list[str]) -> dict[str, list[str]]:
    where = {}
    for pair in pairs:
        key, sep, values = pair.partition("=")
        if not sep or not key.strip() or not values.strip():
            raise UsageError(f"--val-where {pair!r}: expected LABEL=VALUE[,VALUE...], e.g. style=old,proud")
        where[key.strip()] = [v.strip() for v in values.split(",") if v.strip()]
    return where


def _synth_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards synth", description="Procedural labeled motion (humans on smpl22, quadrupeds on smal35) "
                   "into shard sets: the embedded mini data.")
    p.add_argument("--out", default="shards/mini")
    p.add_argument("--scale", type=positive_float, default=1.0, help="multiply every set's clip count")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--fps", type=positive_float, default=20.0, help=f"frames per second, at most {MAX_FPS:g}")
    p.add_argument("--val-fraction", type=nonneg_float, default=0.15)
    p.add_argument("--max-clips", type=positive_int, default=32, help="clips per shard at most")
    args = p.parse_args(argv)
    command = "omg shards synth " + shlex.join(argv)
    out = check_output_dir(args.out)
    with removing_created(*(out / subdir for subdir, *_ in MINI_SETS)):  # a failed set removes the ones before it
        for subdir, skeleton, representation, clips in MINI_SETS:
            options = {"num_clips": max(1, round(clips * args.scale)), "seed": args.seed}
            for summary in build("synth", out / subdir, representation, skeleton, args.fps,
                                 val_fraction=args.val_fraction, max_clips=args.max_clips, options=options, command=command):
                print(summary)


def batch_composition(shard_dir: str | Path, batch_size: int, shuffle_buffer: int, batches: int = 50) -> str:
    """How fair a sample of the set a training batch is: the distinct captions, and the distinct
    values of each clip label (e.g. a take's content), in batches drawn as the training stream
    draws them, against the whole set's."""
    from omg.data.datamodule import ClipDataset, MotionDataModule, MotionStream
    from omg.data.windows import WindowSampler

    data = MotionDataModule(str(shard_dir), verify_shards=False)
    stream = MotionStream(data.train_urls, rank=0, batches=batches, batch_size=batch_size,
                          windows=WindowSampler(mode="whole"), feature_dim=data.feature_dim,
                          shuffle_buffer=shuffle_buffer, max_bad_fraction=1.0)
    items = list(stream)
    samples = ClipDataset.from_shards(data.train_urls, data.feature_dim, stream.windows, max_bad_fraction=1.0).samples
    groups = {"captions": ([it["text"] for it in items], [s["texts"][0] if s["texts"] else "" for s in samples])}
    for label in sorted({k for s in samples for k in s["meta"]["labels"]}):
        groups[label] = ([str(it["labels"].get(label)) for it in items],
                         [str(s["meta"]["labels"].get(label)) for s in samples])
    parts, unfair = [], False
    for name, (drawn, whole) in groups.items():
        counts = Counter(whole)
        if len(counts) < 2:
            continue
        mean = sum(len(set(drawn[i:i + batch_size])) for i in range(0, len(drawn), batch_size)) / batches
        # what batches drawn independently from the whole set would hold
        fair = sum(1 - (1 - n / len(whole)) ** batch_size for n in counts.values())
        parts.append(f"{name} {mean:.1f} of {len(counts)} (fair: {fair:.1f})")
        unfair |= mean < 0.8 * fair
    if not parts:
        return "no captions or labels to report a batch composition for"
    return (f"a batch of {batch_size} through a shuffle buffer of {shuffle_buffer} holds on average: "
            f"{', '.join(parts)}{'; raise data.shuffle_buffer (or rebuild with --shuffle-buffer)' if unfair else ''}")


def _inspect_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards inspect", description="Summarise a shard set, check every shard against its "
                   "manifest (file, size, sample count, end-of-archive, sha256) and validate every sample. "
                   "Exits 1 when a shard or sample is bad, 2 when a manifest is missing or invalid.")
    p.add_argument("dirs", nargs="+", help="shard directories (with manifest.json)")
    p.add_argument("--batch-size", type=positive_int, default=16, help="batch size of the batch-composition report")
    p.add_argument("--shuffle-buffer", type=positive_int, default=1000,
                   help="the training stream's shuffle buffer (data.shuffle_buffer) for that report")
    args = p.parse_args(argv)
    failures = []
    for d in args.dirs:
        result = check_shards(d)
        print(result.manifest.summary())
        for problem in result.problems:
            print(f"  BAD {problem}")
        n, unhashed = len(result.shards), sum("sha256" not in s.checks for s in result.shards)
        line = f"  {result.verified} of {n} shards verified against the manifest"
        if result.failed:
            line += f", {len(result.failed)} failed ({', '.join(f'{s.name}: {s.error.check}' for s in result.failed)})"
        if unhashed:
            line += f", {unhashed} without a sha256 in the manifest"
        bad_samples = sum(len(s.problems) for s in result.shards)
        print(f"{line}; {result.good} valid samples, {len(result.problems)} problems")
        if not result.failed and result.good:
            print("  " + batch_composition(d, args.batch_size, args.shuffle_buffer))
        if result.failed or bad_samples:
            what = [f"{len(result.failed)} of {n} shards failed verification"] if result.failed else []
            what += [f"{bad_samples} bad samples"] if bad_samples else []
            first = result.problems[0]
            failures.append(f"{result.manifest.dir}: {' and '.join(what)} (first: {first})")
    if failures:
        sys.stdout.flush()
        for failure in failures:
            print(f"omg: error: {failure}", file=sys.stderr)
        raise SystemExit(1)


def shards_main(argv: list[str]) -> None:
    commands = {"build": _build_main, "synth": _synth_main, "inspect": _inspect_main}
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: omg shards {build,synth,inspect} [options]\n\n"
              "  build    import motion from a registered data source into shards\n"
              "  synth    generate the procedural mini dataset into shards\n"
              "  inspect  summarise shard sets and validate every sample")
        return
    if argv[0] not in commands:
        raise UsageError(f"unknown shards command {argv[0]!r}; choose from {', '.join(commands)}")
    commands[argv[0]](argv[1:])


if __name__ == "__main__":
    shards_main(sys.argv[1:])
