"""``omg shards build|synth|merge|inspect``: motion from a registered data source into WebDataset shard
sets (``build``), the procedural mini data (``synth``), the parts of an array build joined into
one set (``merge``), and a set's summary and validation (``inspect``). ``build`` is also the
library function the commands and tests call."""

from __future__ import annotations

import hashlib
import inspect
import logging
import math
import sys
import types
import typing
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from omg.data.shards import BuildProgress, EncodedClip, ShardWriter, check_shards, merge_shard_sets, write_shards
from omg.errors import UsageError
from omg.files import check_output_dir, read_text, removing_created
from omg.motion import Clip, get_representation
from omg.registry import DATA_SOURCES
from omg.skeleton import get_skeleton
from omg.tools.args import (
    Fraction,
    NonNegativeInt,
    NonNegativeSeconds,
    PositiveFiniteFloat,
    PositiveInt,
    Seed,
    number_type,
    run_subcommands,
)

MAX_FPS = 1000.0
Fps = number_type("Fps", float, [(">", 0.0), ("<=", MAX_FPS)], f"a number of frames per second in (0, {MAX_FPS:g}]")

# What `omg shards synth` builds by default: the embedded mini data in shards/mini.
# (subdirectory, skeleton, representation, clips)
MINI_SETS = (
    ("human263", "smpl22", "humanml3d263", 100),
    ("animal_maa", "smal35", "maa", 56),
    ("human_maa", "smpl22", "maa", 100),  # OmniMotionGPT's human domain (configs/mini/omgpt.yaml)
    ("animal_quatvel", "smal35", "quatvel", 112),  # habit transfer: 16 clips of each species, category = species
)


def in_val_split(clip_id: str, val_fraction: float) -> bool:
    """A stable split: the same id lands in the same split whatever else is in the set."""
    h = int.from_bytes(hashlib.sha1(clip_id.encode()).digest()[:8], "big") / 2**64
    return h < val_fraction


def in_val_labels(clip: Clip | EncodedClip, val_where: dict[str, list[str]]) -> bool:
    """A split by take: the clip's labels match every ``key: [values]`` of ``val_where``."""
    return all(str(clip.labels.get(key)) in values for key, values in val_where.items())


def in_part(items: Iterable, part: int, parts: int) -> Iterator:
    """Part ``part`` of ``parts`` of a source's items: every ``parts``-th item from the ``part``-th
    on, in the source's order (so a part of a folder sorted by name mixes its subfolders); the
    parts together hold every item once. Items are picked before they are read (``LazyItem``), so
    a part reads only its own files."""
    for index, item in enumerate(items):
        if index % parts == part:
            yield item


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
    workers: int = 1,
    part: int = 0,
    parts: int = 1,
    progress: float | None = None,
) -> list:
    """Build a shard set (``out``, or ``out/train`` and ``out/val`` with a validation split).

    The source is read once (both splits in one pass) by ``workers`` processes; the shards are
    the same for any number of workers. ``part``/``parts``: build only every ``parts``-th source
    item from the ``part``-th (``omg shards merge`` joins the parts). ``progress``: a progress
    line on stderr every this many seconds (None: none).

    Every argument is checked before a folder is made; a build that fails removes the folders
    it created (an existing ``out`` stays, and with it the shards an interrupted build finished)."""
    if not _is_number(fps) or not 0 < fps <= MAX_FPS:
        raise UsageError(f"--fps must be a number in (0, {MAX_FPS:g}], got {fps!r}")
    if not _is_number(val_fraction) or not 0.0 <= val_fraction < 1.0:
        raise UsageError(f"--val_fraction must be in [0, 1), got {val_fraction!r}")
    if not _is_number(max_clips) or isinstance(max_clips, float) or max_clips < 1:
        raise UsageError(f"--max_clips must be a positive integer, got {max_clips!r}")
    if not _is_number(max_mb) or max_mb * 2**20 < 1:
        raise UsageError(f"--max_mb must be a positive number of megabytes (at least 1 byte), got {max_mb!r}")
    if not all(_is_number(v) and not isinstance(v, float) for v in (workers, part, parts)) or workers < 1 or parts < 1:
        raise UsageError(f"--workers and --parts must be integers >= 1, got {workers!r} and {parts!r}")
    if not 0 <= part < parts:
        raise UsageError(f"--part must be in [0, --parts), i.e. 0 to {parts - 1}, got {part!r}")
    # plain numbers: the argument parser's checked subclasses of them do not travel to worker processes
    fps, val_fraction, max_mb = float(fps), float(val_fraction), float(max_mb)
    max_clips, workers, part, parts = int(max_clips), int(workers), int(part), int(parts)
    open_source = DATA_SOURCES.get(source)
    options = _check_options(source, open_source, options or {})
    rep = get_representation(representation, get_skeleton(skeleton))
    out = check_output_dir(out)
    if not _is_number(shuffle_buffer) or isinstance(shuffle_buffer, float) or shuffle_buffer < 0:
        raise UsageError(f"--shuffle_buffer must be an integer >= 0, got {shuffle_buffer!r}")
    if val_where and val_fraction > 0:
        raise UsageError("give --val_fraction (a random split) or --val_where (a split by label), not both")
    splits = ["train", "val"] if val_fraction > 0 or val_where else [""]

    def route(clip: EncodedClip) -> str:
        in_val = in_val_labels(clip, val_where) if val_where else in_val_split(clip.id, val_fraction)
        return "val" if in_val else "train"

    try:
        with removing_created(*(out / name for name in splits)):
            items = open_source(input=input, skeleton=rep.skeleton, fps=fps, **options)
            stats = getattr(items, "stats", {}).get(rep.name)  # a source's published normalisation (SourceItems)
            total = _count(items)
            if parts > 1:
                items = in_part(items, part, parts)
                total = None if total is None else len(range(part, total, parts))
            items = shuffled(items, shuffle_buffer, seed)
            writers = {name: ShardWriter(out / name, rep, fps, max_clips, int(max_mb * 2**20), command, log=log,
                                         stats=stats) for name in splits}
            meter = BuildProgress(total, progress, label=f"omg shards build {out}") if progress else None
            return write_shards(items, writers, route if splits != [""] else None, workers, meter)
    except UnicodeDecodeError as e:  # a text file an option names (a YAML joint map, ...) in another encoding
        named = [f"--option.{k} {v}" for k, v in options.items() if isinstance(v, str) and not _is_utf8_file(v)]
        which = f"{named[0]}: not a UTF-8 text file" if named else "a file is not UTF-8 text"
        raise UsageError(f"{which} ({e.reason} at offset {e.start}); save it as UTF-8") from None


def _count(items) -> int | None:
    """How many items a source holds, where it knows (a list of files), else None."""
    inner = getattr(items, "items", items)  # SourceItems wraps them
    try:
        return len(inner)
    except TypeError:
        return None


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
    """``--option.KEY`` keys against the source's parameters, values against their annotations.

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
            raise UsageError(f"--option.{key} {value}: the key must be a name such as num_clips")
        if key in RESERVED_OPTIONS:
            raise UsageError(f"--option.{key}: give it as {RESERVED_OPTIONS[key]}")
        if key not in params and not open_ended:
            raise UsageError(f"--option.{key}: the {name} source has no such option; "
                             f"its options: {', '.join(known) or 'none'}")
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if number and not (math.isfinite(value) and value >= 0):
            raise UsageError(f"--option.{key} {value}: expected a finite number >= 0")
        allowed = _allowed_types(hints.get(key))
        if allowed and not _fits(value, allowed):
            kinds = " or ".join(dict.fromkeys(_KINDS[t] for t in allowed))
            raise UsageError(f"--option.{key} {value!r}: the {name} source expects {kinds}")
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


def shards_build(
    source: str,
    out: Path,
    input: str | None = None,
    representation: str = "humanml3d263",
    skeleton: str = "smpl22",
    fps: Fps = 30.0,
    val_fraction: Fraction = 0.0,
    max_clips: PositiveInt = 1000,
    max_mb: PositiveFiniteFloat = 256.0,
    val_where: dict[str, Any] | None = None,
    shuffle_buffer: NonNegativeInt = 1000,
    seed: Seed = 0,
    option: dict[str, Any] | None = None,
    workers: PositiveInt = 1,
    part: NonNegativeInt = 0,
    parts: PositiveInt = 1,
    progress: PositiveFiniteFloat = 5.0,
    command: str = "omg shards build",
) -> list:
    """Import motion from a registered data source into shards.

    With --val_fraction or --val_where the clips go to out/train and out/val.

    Args:
        source: the registered data source (omg plugins lists them)
        out: output directory
        input: the source's input (a directory or file), if it takes one
        representation: the motion representation the shards store
        skeleton: the skeleton the motion is retargeted to
        fps: frames per second
        val_fraction: put this share of clips in out/val, the rest in out/train
        max_clips: clips per shard at most
        max_mb: megabytes per shard at most
        val_where: put the clips whose label LABEL is one of the values in out/val (a split by take; every
            label must match), e.g. --val_where.style old,proud (or a list [old, proud])
        shuffle_buffer: write clips in a seeded random order through a buffer of this many clips (0: input order)
        seed: seed of the clip order
        option: options passed to the source, e.g. --option.num_clips 100 (or a mapping {num_clips: 100})
        workers: processes that read, retarget and encode clips (the shards are the same for any number)
        part: build this part of the source's items (0-based; for array jobs, with --parts)
        parts: split the source's items into this many parts (every parts-th item from the part-th); join the
            parts' outputs with omg shards merge
        progress: print a progress line (items read, clips, skipped, rate, time left) to stderr every this many
            seconds
        command: the command line, recorded in the manifest

    Returns:
        The build summaries, one per split.
    """
    summaries = build(source, out, representation, skeleton, fps, input, val_fraction, max_clips, max_mb, option,
                      command, log=print, val_where=_val_where(val_where), shuffle_buffer=shuffle_buffer, seed=seed,
                      workers=workers, part=part, parts=parts, progress=progress)
    for summary in summaries:
        print(summary)
    return summaries


def _val_where(val_where: dict[str, Any] | None) -> dict[str, list[str]]:
    """``--val_where`` as LABEL -> values (labels compare as text); a value given as text may list
    several, comma-separated."""
    where = {}
    for key, values in (val_where or {}).items():
        if isinstance(values, dict):
            raise UsageError(f"--val_where.{key}: expected a value or a list of values, got {values!r}")
        values = values.split(",") if isinstance(values, str) else values if isinstance(values, list) else [values]
        where[key] = [str(v).strip() for v in values if str(v).strip()]
        if not where[key]:
            raise UsageError(f"--val_where.{key}: give the label values that go to out/val, "
                             f"e.g. --val_where.{key} old,proud")
    return where


def merge(parts: list[str | Path], out: str | Path, command: str = "", link: bool = False, log=print) -> list:
    """Join the outputs of ``build --part i --parts n``: each part a shard set, or a folder of
    split sets (``train/``, ``val/``), joined split by split. Returns the merged manifests."""
    parts = [Path(p) for p in parts]
    if not parts:
        raise UsageError("give the part folders to merge")
    for p in parts:
        if not p.is_dir():
            raise UsageError(f"{p}: no such folder (a part built with omg shards build --part I --parts N)")
    if (parts[0] / "manifest.json").exists() or (parts[0] / "build-state.json").exists():
        splits = [""]
    else:
        splits = sorted(d.name for d in parts[0].iterdir() if (d / "manifest.json").exists()
                        or (d / "build-state.json").exists())
        if not splits:
            raise UsageError(f"{parts[0]}: neither a shard set (manifest.json) nor a folder of them (train/, val/)")
    out = check_output_dir(out)
    with removing_created(*(Path(out) / s for s in splits)):
        return [merge_shard_sets([p / s for p in parts], Path(out) / s, command, link=link, log=log) for s in splits]


def shards_merge(parts: list[str], out: Path, link: bool = False, command: str = "omg shards merge") -> None:
    """Join the parts of an array build into one shard set.

    Each part is the --out of one omg shards build --part I --parts N (a set, or train/ and
    val/ sets, merged split by split). Shards keep their bytes and sha256 and are renamed in
    part order; clip and frame counts are summed and the mean/std are pooled from the parts'
    raw sums. Parts must share representation, skeleton and frame rate.

    Args:
        parts: the part folders, in order
        out: output directory
        link: hard-link the shards instead of copying them (same file system; only their size is checked,
            where a copy checks each shard's sha256 against its part's manifest)
        command: the command line, recorded in the manifest
    """
    for manifest in merge(parts, out, command, link=link):
        print(manifest.summary())


def shards_synth(
    out: Path = Path("shards/mini"),
    scale: PositiveFiniteFloat = 1.0,
    seed: Seed = 0,
    fps: Fps = 20.0,
    val_fraction: Fraction = 0.15,
    max_clips: PositiveInt = 32,
    command: str = "omg shards synth",
) -> None:
    """Generate the procedural mini dataset into shards.

    Labeled humans on smpl22 and quadrupeds on smal35: the embedded mini data in shards/mini.

    Args:
        out: output directory (one shard set per subfolder)
        scale: multiply every set's clip count
        seed: seed of the motion and captions
        fps: frames per second
        val_fraction: put this share of clips in the val split
        max_clips: clips per shard at most
        command: the command line, recorded in the manifests
    """
    out = check_output_dir(out)
    with removing_created(*(out / subdir for subdir, *_ in MINI_SETS)):  # a failed set removes the ones before it
        for subdir, skeleton, representation, clips in MINI_SETS:
            options = {"num_clips": max(1, round(clips * scale)), "seed": seed}
            for summary in build("synth", out / subdir, representation, skeleton, fps,
                                 val_fraction=val_fraction, max_clips=max_clips, options=options, command=command):
                print(summary)


def batch_composition(shard_dir: str | Path, batch_size: int, shuffle_buffer: int, batches: int = 50) -> str:
    """How fair a sample of the set a training batch is: the distinct captions, and the distinct
    values of each clip label (e.g. a take's content), in batches drawn as the training stream
    draws them, against the whole set's."""
    from omg.data.loaders import ClipDataset, MotionStream, resolve_shards
    from omg.data.windows import WindowSampler

    urls, manifest, _ = resolve_shards(str(shard_dir))  # unverified: `inspect` has just checked every shard
    feature_dim = manifest["feature_dim"]
    windows = WindowSampler(min_len=1, mode="whole")  # every clip
    # `inspect` has reported every bad sample once already; the stream would warn at each of its visits
    data_log = logging.getLogger(MotionStream.__module__)
    level = data_log.level
    data_log.setLevel(logging.ERROR)
    try:
        samples = ClipDataset.from_shards(urls, feature_dim, windows, max_bad_fraction=1.0).samples
        # a small set's mixing shows in two passes over it as well as in more (each pass re-reads every shard)
        batches = max(1, min(batches, -(-2 * len(samples) // batch_size)))
        stream = MotionStream(urls, rank=0, batches=batches, batch_size=batch_size, windows=windows,
                              feature_dim=feature_dim, shuffle_buffer=shuffle_buffer, max_bad_fraction=1.0)
        items = list(stream)
    finally:
        data_log.setLevel(level)
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
            f"{', '.join(parts)}{'; raise data.shuffle_buffer (or rebuild with --shuffle_buffer)' if unfair else ''}")


def mixture_locations(arg: str) -> list[str]:
    """The shard sets ``inspect`` checks for one argument: a set (directory or URL) is itself; a
    mixture config (a YAML/JSON file with ``data.train``, or the list itself as YAML) prints each
    set's clips, frames, hours and share of the samples, and gives its sets."""
    from omg.data.mixture import load_mixture

    where = ""  # the file a mixture comes from, for messages
    if arg.lstrip().startswith(("[", "{")):
        train = _yaml(arg, "the mixture")
    elif arg.endswith((".yaml", ".yml")) and not Path(arg).exists():
        raise UsageError(f"{arg}: no such mixture config")
    elif arg.endswith((".yaml", ".yml", ".json")) and Path(arg).is_file():
        where, config = f"{arg}: ", _yaml(read_text(arg, "the mixture config"), arg)
        data = config.get("data") if isinstance(config, dict) else None
        train = data.get("train") if isinstance(data, dict) else config if isinstance(config, list) else None
        if not train:
            raise UsageError(f"{arg}: no data.train (a list of {{path: DIR_OR_URL, weight: W}}) in it")
    else:
        return [arg]
    try:
        mixture = load_mixture(train, "data.train")
    except UsageError as e:
        raise UsageError(f"{where}{e}") from None
    for line in mixture.describe():
        print(line)
    return [s.manifest.location for s in mixture.sets]


def _yaml(text: str, what: str):
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise UsageError(f"{what}: not valid YAML ({str(e).splitlines()[0]})") from None


def shards_inspect(dirs: list[str], batch_size: PositiveInt = 16, shuffle_buffer: PositiveInt = 1000,
                   timeout: NonNegativeSeconds = 600.0) -> None:
    """Summarise shard sets and validate every sample.

    Checks every shard against its manifest (file, size, sample count, end-of-archive, sha256)
    and validates every sample. Exits 1 when a shard or sample is bad, 2 when a manifest is
    missing or invalid. A mixture config (a YAML with data.train, or the list itself) first
    prints each set's clips, frames, hours and share of the samples.

    Args:
        dirs: shard sets (directories with manifest.json, or set URLs such as pipe:cat DIR/manifest.json)
            or mixture configs
        batch_size: batch size of the batch-composition report
        shuffle_buffer: the training stream's shuffle buffer (data.shuffle_buffer) for that report
        timeout: seconds the read of one shard may take before inspect stops with one line (a stalled
            read: a hung mount, a pipe: command that prints nothing); 0 waits forever
    """
    failures = []
    for d in [location for arg in dirs for location in mixture_locations(arg)]:
        result = check_shards(d, timeout, "--timeout")
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
            print("  " + batch_composition(d, batch_size, shuffle_buffer))
        if result.failed or bad_samples:
            what = [f"{len(result.failed)} of {n} shards failed verification"] if result.failed else []
            what += [f"{bad_samples} bad samples"] if bad_samples else []
            first = result.problems[0]
            failures.append(f"{result.manifest.location}: {' and '.join(what)} (first: {first})")
    if failures:
        sys.stdout.flush()
        for failure in failures:
            print(f"omg: error: {failure}", file=sys.stderr)
        raise SystemExit(1)


COMMANDS = {
    "build": (shards_build, {}),
    "synth": (shards_synth, {}),
    "inspect": (shards_inspect, {"positional": "dirs", "nargs": "+"}),
    "merge": (shards_merge, {"positional": "parts", "nargs": "+"}),
}


def main(argv: list[str]) -> None:
    run_subcommands("omg shards", "Build, synthesise, merge and inspect WebDataset motion shards.", COMMANDS, argv)
