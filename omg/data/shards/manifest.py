"""A shard set's ``manifest.json``: what it records (shards, sizes, sha256, statistics), its checks, and
``merge_shard_sets``, which joins the sets built from parts of a source into one."""

from __future__ import annotations

import hashlib
import json
import re
import shlex
import tarfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omg.data.shards.remote import _local_path, manifest_url, read_url, sibling_url, url_file_name
from omg.data.shards.schema import BUILD_STATE, MANIFEST, SCHEMA_VERSION, SHARD_NAME, SHARD_PATTERN, FeatureStats
from omg.errors import UsageError
from omg.files import atomic_path, write_json
from omg.motion import DataSpec, Representation


def manifest_data(representation: Representation, fps: float, shards: list[dict], stats: FeatureStats,
                  skipped: dict[str, int], command: str = "",
                  fixed: tuple[np.ndarray, np.ndarray] | None = None, **extra) -> dict:
    """A set's manifest: its shards, and the mean/std finalized once from the raw sums over all
    its frames (or ``fixed``, a published normalisation)."""
    mean, std = fixed or representation.finalize_stats(*stats.mean_std())
    skeleton = representation.skeleton
    return {
        "schema_version": SCHEMA_VERSION,
        "representation": representation.name,
        "feature_dim": representation.dim,
        "skeleton": skeleton.name,
        "skeleton_def": skeleton.to_dict(),
        "fps": fps,
        "num_clips": sum(s["clips"] for s in shards),
        "num_frames": stats.count,
        "num_shards": len(shards),
        "skipped": skipped,
        "shards": shards,
        "mean": np.asarray(mean).tolist(),
        "std": np.asarray(std).tolist(),
        "stats_origin": "source" if fixed is not None else "measured",
        # the raw per-feature sums behind a measured mean/std: sets (merged parts, mixtures)
        # pool these, since a finalized std (e.g. humanml3d263's group average) cannot be pooled
        "sums": stats.to_json(),
        "command": command,
        **extra,
    }


def _clip_ids(shard: Path) -> set[str]:
    """The sample keys of a local shard, as WebDataset groups its members, from the tar headers alone."""
    from webdataset.tariterators import base_plus_ext

    try:
        with tarfile.open(shard) as tar:
            return {key for key, _ in map(base_plus_ext, tar.getnames()) if key}
    except (OSError, tarfile.TarError) as e:
        raise UsageError(f"{shard}: not a readable shard ({e}); rebuild that part") from None


def _check_disjoint(manifests: list[Manifest]) -> None:
    """Each part once and no clip in two parts: a merge would otherwise train on those clips twice
    as often and pool their statistics twice."""
    owners: dict[str, Path] = {}  # clip id -> the part holding it
    seen: dict[Path, Path] = {}  # resolved folder -> the part as given
    for m in manifests:
        if (resolved := m.dir.resolve()) in seen:
            raise UsageError(f"cannot merge {m.dir}: the same part as {seen[resolved]}, given twice; "
                             "give each part once")
        seen[resolved] = m.dir
        for path in m.shard_paths:
            ids = _clip_ids(path)
            if clash := next((i for i in sorted(ids) if i in owners), None):
                raise UsageError(f"cannot merge {m.dir} and {owners[clash]}: they overlap (both hold clip {clash}); "
                                 "parts of one build hold disjoint clips")
            owners.update(dict.fromkeys(ids, m.dir))


def merge_shard_sets(parts: list[str | Path], out: str | Path, command: str = "", link: bool = False,
                     log=print) -> Manifest:
    """Join finished shard sets (the parts of an array build) into one set at ``out``: their
    shards in part order, renamed ``shard-NNNNNN.tar`` (bytes and sha256 unchanged), counts
    summed and the statistics pooled from the parts' raw sums, finalized once.

    Parts must agree on representation, feature size, skeleton and frame rate. Each shard is
    copied and checked against its part's sha256 as it is copied (``link``: hard-linked, on
    the same file system, and only its size checked)."""
    import os

    manifests = [Manifest.load(p) for p in parts]
    if not manifests:
        raise UsageError("give the part folders to merge")
    first = manifests[0]
    for m in manifests[1:]:
        for key in ("representation", "feature_dim", "skeleton", "skeleton_def", "fps"):
            if m.data.get(key) != first.data.get(key):
                what = "its skeleton definition differs" if key == "skeleton_def" else (
                    f"{key} {m.data.get(key)!r}, but {first.dir} has {first.data.get(key)!r}")
                raise UsageError(f"cannot merge {m.dir}: {what}; parts must be built with the same settings")
    if missing := [str(m.dir) for m in manifests if m.sums is None]:
        raise UsageError(f"{missing[0]}: its manifest has no raw sums to pool statistics from; rebuild that part")
    _check_disjoint(manifests)
    out = Path(out)
    if out.exists() and (any(out.glob("shard-*.tar")) or (out / MANIFEST).exists()):
        raise UsageError(f"--out {out}: already holds a shard set; choose an empty folder")
    if any(out.resolve() == m.dir.resolve() for m in manifests):
        raise UsageError(f"--out {out}: is one of the parts; choose another folder")
    out.mkdir(parents=True, exist_ok=True)
    shards, stats, skipped = [], FeatureStats(), {}
    for m in manifests:
        stats.merge(m.sums)
        for reason, n in m.data.get("skipped", {}).items():
            skipped[reason] = skipped.get(reason, 0) + n
        for entry, path in zip(m["shards"], m.shard_paths):
            name = SHARD_PATTERN.format(len(shards))
            size = entry.get("bytes")
            if link:
                if size is not None and (found := path.stat().st_size) != size:
                    raise UsageError(f"{path}: {found} bytes, its manifest says {size}; rebuild that part")
                with atomic_path(out / name) as tmp:
                    tmp.unlink(missing_ok=True)
                    os.link(path, tmp)
                digest = entry.get("sha256")
            else:
                with atomic_path(out / name) as tmp, open(path, "rb") as src, open(tmp, "wb") as dst:
                    hasher = hashlib.sha256()
                    while chunk := src.read(1 << 22):
                        hasher.update(chunk)
                        dst.write(chunk)
                digest = hasher.hexdigest()
                if entry.get("sha256") not in (None, digest):
                    (out / name).unlink()
                    raise UsageError(f"{path}: its sha256 does not match its manifest (garbled or replaced); "
                                     "rebuild that part")
                size = (out / name).stat().st_size
            shards.append({"name": name, "clips": entry.get("clips", 0), "frames": entry.get("frames", 0),
                           "bytes": size, "sha256": digest})
    from omg.motion import get_representation
    from omg.skeleton import get_skeleton

    representation = get_representation(first["representation"], get_skeleton(first["skeleton"]))
    fixed = None
    if all(m.data.get("stats_origin") == "source" for m in manifests) and all(
            m.data["mean"] == first.data["mean"] and m.data["std"] == first.data["std"] for m in manifests):
        fixed = (first.mean, first.std)  # the published normalisation every part carries
    manifest = manifest_data(representation, first["fps"], shards, stats, skipped, command, fixed,
                             parts=[str(m.dir) for m in manifests])
    manifest["skeleton_def"] = first["skeleton_def"]
    write_json(out / MANIFEST, manifest)
    log(f"merged {len(manifests)} parts into {out}: {manifest['num_clips']} clips, {stats.count} frames "
        f"in {len(shards)} shards")
    return Manifest.load(out)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _manifest_problem(data) -> str | None:
    """What is wrong with a parsed manifest, in a few words, or None."""
    if not isinstance(data, dict):
        return f"not a JSON object but a JSON {type(data).__name__}"
    if "schema_version" not in data:
        return "missing key 'schema_version'"
    if data["schema_version"] != SCHEMA_VERSION:
        return f"schema version {data['schema_version']!r}, this omg reads {SCHEMA_VERSION}; rebuild the shards"
    required = ("representation", "skeleton", "feature_dim", "fps", "shards", "mean", "std")
    if missing := [k for k in required if k not in data]:
        return f"missing key{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}"
    for key in ("representation", "skeleton"):
        if not isinstance(data[key], str) or not data[key]:
            return f"{key!r} must be a non-empty string, got {data[key]!r}"
    if not _is_int(data["feature_dim"]) or data["feature_dim"] < 1:
        return f"'feature_dim' must be a positive integer, got {data['feature_dim']!r}"
    if not _is_number(data["fps"]) or not data["fps"] > 0:
        return f"'fps' must be a positive number, got {data['fps']!r}"
    for key in ("mean", "std"):
        values = data[key]
        if not isinstance(values, list) or not all(_is_number(v) for v in values):
            return f"{key!r} must be a list of numbers"
        if len(values) != data["feature_dim"]:
            return f"{key!r} has {len(values)} values, 'feature_dim' is {data['feature_dim']}"
        if not np.isfinite(values).all() or (key == "std" and min(values) <= 0):
            return f"{key!r} must be {'positive and ' if key == 'std' else ''}finite"
    if "sums" in data:
        sums = data["sums"]
        if not (isinstance(sums, dict) and _is_int(sums.get("count")) and sums["count"] >= 0
                and all(isinstance(sums.get(k), list) and len(sums[k]) == data["feature_dim"]
                        and all(_is_number(v) for v in sums[k]) for k in ("total", "total_sq"))):
            return "'sums' must be {count, total, total_sq} with 'feature_dim' values each"
    for key in ("num_clips", "num_frames", "num_shards"):
        if key in data and (not _is_int(data[key]) or data[key] < 0):
            return f"{key!r} must be a non-negative integer, got {data[key]!r}"
    shards = data["shards"]
    if not isinstance(shards, list) or not shards:
        return "'shards' must be a non-empty list of shard entries"
    names = set()
    for i, entry in enumerate(shards):
        if not isinstance(entry, dict):
            return f"shards[{i}] must be an object, got {entry!r}"
        name = entry.get("name")
        if not isinstance(name, str) or not SHARD_NAME.fullmatch(name):
            return (f"shards[{i}] needs a 'name' of the form shard-NNNNNN.tar (a file in the manifest's directory, as "
                    f"`omg shards build` names them), got {name!r}")
        if name in names:
            return f"shard {name} is listed twice"
        names.add(name)
        for key in ("clips", "frames", "bytes"):
            if key in entry and (not _is_int(entry[key]) or entry[key] < 0):
                return f"shard {name}: {key!r} must be a non-negative integer, got {entry[key]!r}"
        sha = entry.get("sha256")
        if sha is not None and not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
            return f"shard {name}: 'sha256' must be 64 lowercase hex digits, got {sha!r}"
    if "num_shards" in data and data["num_shards"] != len(shards):
        return f"'num_shards' is {data['num_shards']} but {len(shards)} shards are listed"
    if ("num_clips" in data and all("clips" in s for s in shards)
            and data["num_clips"] != sum(s["clips"] for s in shards)):
        return f"'num_clips' is {data['num_clips']} but the shards hold {sum(s['clips'] for s in shards)} clips"
    return None


@dataclass
class Manifest:
    """The parsed ``manifest.json`` of a shard set.

    ``load`` checks the schema: a manifest that is not JSON, lacks a key, has a value of the
    wrong type or another schema version is a ``UsageError`` naming the file and the problem.
    Per shard it records ``name`` and, in manifests written by ``ShardWriter``, ``clips``
    (samples), ``frames``, ``bytes`` (file size) and ``sha256`` (of the file); the last three
    are optional for readers: a check whose value is not recorded is not made.

    ``url``: where a set on object storage or behind a ``pipe:`` command was fetched from (the
    manifest's own URL); its shards are the same URL with the shard's name in place of
    ``manifest.json`` (``shard_urls``). None for a set on a local disk.
    """

    path: Path
    data: dict
    url: str | None = None
    _by_name: dict | None = field(default=None, init=False, repr=False, compare=False)  # shard entries by name

    @classmethod
    def load(cls, location: str | Path) -> Manifest:
        """A set's manifest from a local directory (or its manifest.json) or a URL: a directory URL
        (``s3://bucket/sets/amass``), a manifest URL (``gs://…/amass/manifest.json``) or a command
        that prints the manifest (``pipe:cat /data/amass/manifest.json``)."""
        local = _local_path(str(location))
        if local is None:
            return cls._fetch(manifest_url(str(location)))
        path = local if local.name == MANIFEST and not local.is_dir() else local / MANIFEST
        if not path.exists():
            hint = (" (an unfinished build: run the same build command again)"
                    if (path.parent / BUILD_STATE).exists() else "")
            raise UsageError(f"no {MANIFEST} in {path.parent}{hint}; "
                             "build shards with `omg shards build` or `omg shards synth`")
        try:
            data = path.read_bytes()
        except OSError as e:
            raise UsageError(f"{path}: cannot be read ({e.strerror or e})") from None
        return cls(path, cls._parse(data, str(path)))

    @classmethod
    def _fetch(cls, url: str) -> Manifest:
        try:
            data = read_url(url)
        except (OSError, ValueError) as e:
            raise UsageError(f"{url}: the manifest cannot be fetched ({e})") from None
        return cls(Path(MANIFEST), cls._parse(data, url), url)

    @staticmethod
    def _parse(raw: bytes, where: str) -> dict:
        try:
            data = json.loads(raw)
        except UnicodeDecodeError:
            raise UsageError(f"{where}: not a text file (invalid UTF-8); rebuild the shards") from None
        except json.JSONDecodeError as e:
            raise UsageError(f"{where}: not valid JSON ({e.msg} at line {e.lineno} column {e.colno}); "
                             "rebuild the shards") from None
        if problem := _manifest_problem(data):
            hint = "" if "schema version" in problem else "; rebuild the shards"
            raise UsageError(f"{where}: invalid manifest: {problem}{hint}")
        return data

    @property
    def dir(self) -> Path:
        return self.path.parent

    @property
    def location(self) -> str:
        """The set as messages name it: its directory, or the URL its manifest came from."""
        return self.url or str(self.dir)

    @property
    def shard_urls(self) -> list[str]:
        """Every shard's path, or URL for a fetched set (what ``iter_tar`` opens)."""
        if self.url is None:
            return [str(p) for p in self.shard_paths]
        quote = shlex.quote if self.url.startswith("pipe:") else str  # a shell reads a pipe: command
        return [sibling_url(self.url, MANIFEST, quote(s["name"])) for s in self.data["shards"]]

    @property
    def shard_paths(self) -> list[Path]:
        return [self.dir / s["name"] for s in self.data["shards"]]

    def entry(self, url: str | Path) -> dict | None:
        """The manifest's entry for a shard path or URL (matched by file name; in a ``pipe:``
        command, by the last word that names a file), or None."""
        if self._by_name is None:  # one dict, not a scan per shard: a set may have 10^4 shards
            self._by_name = {s["name"]: s for s in self.data["shards"]}
        return self._by_name.get(url_file_name(str(url)))

    def expected(self, url: str | Path) -> dict:
        """What the manifest records about one shard, as keyword arguments of ``iter_tar``:
        ``{"sha256": hex, "samples": clips, "size": bytes}`` (only those recorded; ``{}`` for a
        shard the manifest does not list)."""
        entry = self.entry(url) or {}
        found = {"sha256": entry.get("sha256"), "samples": entry.get("clips"), "size": entry.get("bytes")}
        return {k: v for k, v in found.items() if v is not None}

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.data["mean"], dtype=np.float32)

    @property
    def std(self) -> np.ndarray:
        return np.asarray(self.data["std"], dtype=np.float32)

    @property
    def sums(self) -> FeatureStats | None:
        """The raw per-feature sums of the set's frames (None in manifests written before omg
        recorded them): what pooled statistics of several sets are computed from."""
        return FeatureStats.from_json(self.data["sums"]) if "sums" in self.data else None

    def __getitem__(self, key: str):
        return self.data[key]

    def spec(self) -> DataSpec:
        """What a model needs to know about its data, stored in its checkpoint."""
        return DataSpec.coerce(self.data, self.url or f"{self.dir / MANIFEST}")

    def summary(self) -> str:
        d = self.data
        shards = d["shards"]
        clips = d.get("num_clips", sum(s.get("clips", 0) for s in shards))
        frames = d.get("num_frames", sum(s.get("frames", 0) for s in shards))
        hours = frames / d["fps"] / 3600
        return (
            f"{self.location}: {clips} clips, {frames} frames ({hours:.2f} h at {d['fps']} fps) "
            f"in {len(shards)} shards; representation {d['representation']} ({d['feature_dim']}-d) "
            f"on {d['skeleton']}; built by: {d.get('command') or 'unknown'}"
        )
