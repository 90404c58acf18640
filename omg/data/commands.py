"""``omg shards build|synth|inspect``."""

from __future__ import annotations

import hashlib
import shlex
import sys
from pathlib import Path
from typing import Iterable, Iterator

import yaml

from omg.cli import ToolParser
from omg.data.shards import ShardWriter, validate
from omg.errors import UsageError
from omg.motion import Clip, get_representation
from omg.registry import DATA_SOURCES
from omg.skeleton import get_skeleton

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


def _split(items: Iterable[Clip | Exception], val_fraction: float, want_val: bool) -> Iterator[Clip | Exception | None]:
    for item in items:
        if isinstance(item, Clip):
            yield item if in_val_split(item.id, val_fraction) == want_val else None
        else:  # a failed item is counted once, in the training split
            yield None if want_val else item


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
) -> list:
    """Build a shard set (``out``, or ``out/train`` and ``out/val`` with a validation split)."""
    if not 0.0 <= val_fraction < 1.0:
        raise UsageError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    open_source = DATA_SOURCES.get(source)
    rep = get_representation(representation, get_skeleton(skeleton))
    splits = {"train": False, "val": True} if val_fraction > 0 else {"": False}
    summaries = []
    for name, want_val in splits.items():
        items = open_source(input=input, skeleton=rep.skeleton, fps=fps, **(options or {}))
        stats = getattr(items, "stats", {}).get(rep.name)  # a source's published normalisation (SourceItems)
        if val_fraction > 0:
            items = _split(items, val_fraction, want_val)
        writer = ShardWriter(Path(out) / name, rep, fps, max_clips, int(max_mb * 2**20), command, log=log,
                             stats=stats)
        summaries.append(writer.write(items))
    return summaries


def _parse_options(pairs: list[str]) -> dict:
    options = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise UsageError(f"--option {pair!r} must look like key=value")
        options[key.replace("-", "_")] = yaml.safe_load(value)
    return options


def _build_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards build", description="Import motion from a registered data source into shards.")
    p.add_argument("--config", help="YAML file with any of the options below (command-line values win)")
    p.add_argument("--source", help=f"data source name ({', '.join(DATA_SOURCES.names())})")
    p.add_argument("--input", help="the source's input (a directory or file), if it takes one")
    p.add_argument("--out", help="output directory")
    p.add_argument("--representation", default="humanml3d263")
    p.add_argument("--skeleton", default="smpl22")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--val-fraction", type=float, default=0.0, help="put this share of clips in out/val, the rest in out/train")
    p.add_argument("--max-clips", type=int, default=1000, help="clips per shard at most")
    p.add_argument("--max-mb", type=float, default=256.0, help="megabytes per shard at most")
    p.add_argument("--option", action="append", default=[], help="key=value passed to the source (repeatable)")
    args = p.parse_args(argv)
    if args.config:
        config = yaml.safe_load(Path(args.config).read_text()) if Path(args.config).exists() else None
        if not isinstance(config, dict):
            raise UsageError(f"--config {args.config}: not a YAML mapping file")
        dests = {a.dest for a in p._actions} - {"help", "config"}
        for key, value in config.items():
            dest = key.replace("-", "_")
            if dest not in dests:
                raise UsageError(f"{args.config}: unknown key {key!r}; known keys: {', '.join(sorted(dests))}")
            if getattr(args, dest) == p.get_default(dest):
                setattr(args, dest, value)
    for required in ("source", "out"):
        if not getattr(args, required):
            raise UsageError(f"omg shards build: --{required} is required")
    options = args.option if isinstance(args.option, dict) else _parse_options(args.option)
    command = "omg shards build " + shlex.join(argv)
    for summary in build(args.source, args.out, args.representation, args.skeleton, args.fps, args.input,
                         args.val_fraction, args.max_clips, args.max_mb, options, command, log=print):
        print(summary)


def _synth_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards synth", description="Procedural labeled motion (humans on smpl22, quadrupeds on smal35) "
                   "into shard sets: the embedded mini data.")
    p.add_argument("--out", default="shards/mini")
    p.add_argument("--scale", type=float, default=1.0, help="multiply every set's clip count")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fps", type=float, default=20.0)
    p.add_argument("--val-fraction", type=float, default=0.15)
    p.add_argument("--max-clips", type=int, default=32, help="clips per shard at most")
    args = p.parse_args(argv)
    command = "omg shards synth " + shlex.join(argv)
    for subdir, skeleton, representation, clips in MINI_SETS:
        options = {"num_clips": max(1, round(clips * args.scale)), "seed": args.seed}
        for summary in build("synth", Path(args.out) / subdir, representation, skeleton, args.fps,
                             val_fraction=args.val_fraction, max_clips=args.max_clips, options=options, command=command):
            print(summary)


def _inspect_main(argv: list[str]) -> None:
    p = ToolParser(prog="omg shards inspect", description="Summarise a shard set and validate every sample.")
    p.add_argument("dirs", nargs="+", help="shard directories (with manifest.json)")
    args = p.parse_args(argv)
    failed = False
    for d in args.dirs:
        manifest, good, problems = validate(d)
        print(manifest.summary())
        for problem in problems:
            print(f"  BAD {problem}")
        print(f"  {good} valid samples, {len(problems)} problems")
        failed |= bool(problems)
    if failed:
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
