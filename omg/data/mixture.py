"""Weighted mixtures of shard sets: ``data.train: [{path: shards/amass, weight: 0.7}, …]``.

OMG pretrains on motion gathered from many sources (paper Sec. 3.1); each source is a shard set
and the training stream draws every sample from set k with probability ``share_k = w_k / Σ w``
(``MotionStream``). A set is named by one location: a local directory, a URL pattern of its
shards (``/data/h3d/shard-{000000..000127}.tar``), a directory URL (``s3://bucket/sets/amass``)
or the URL of its manifest (``pipe:cat /data/amass/manifest.json``, any command that prints it:
its shards are read by the same command with the shard's name in place of ``manifest.json``).

Without weights (a plain string or list of strings) the shares are the sets' frame counts:
the mixture is then the sets' concatenation.

Normalisation of a mixture is its own, pooled from the manifests' raw per-feature sums
(``Manifest.sums``) weighted as the stream samples: each set's per-frame moments
``E_k[x]`` and ``E_k[x²]`` are weighted by its share, ``mean = Σ share_k E_k[x]``,
``var = Σ share_k E_k[x²] − mean²``, and the representation finalizes them once
(``finalize_stats``: humanml3d263 averages the std per feature group, which cannot be pooled
after the fact). With frame-proportional shares this is exactly the statistics of the
concatenated clips. A single set keeps its manifest's mean/std, so a published normalisation
(HumanML3D's Mean.npy/Std.npy) stays exact. A manifest written before omg recorded sums is
pooled from its mean/std when its representation's ``finalize_stats`` only floors the std
(exact but for features floored at 1e-4); otherwise it is a one-line error asking for a rebuild.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omg.data.shards import MANIFEST, FeatureStats, Manifest, manifest_url, sibling_url, url_file_name
from omg.errors import UsageError
from omg.motion import DataSpec, Representation, get_representation
from omg.skeleton import get_skeleton

log = logging.getLogger(__name__)

ENTRY_KEYS = ("path", "weight")
ENTRY_FORM = "{path: DIR_OR_URL, weight: W}"


def _is_local(location: str) -> bool:
    return "://" not in location and not location.startswith("pipe:")


@dataclass
class ShardSet:
    """One set of a mixture: where it is, its manifest, the shard URLs it contributes and what
    the manifest records about each of them (``iter_tar`` keyword arguments)."""

    location: str  # as the config names it
    manifest: Manifest
    urls: list[str]  # sorted
    checks: dict[str, dict] = field(default_factory=dict)
    weight: float | None = None  # as given; None: mixed by frames

    def _recorded(self, key: str, total: str) -> int:
        """A count over this set's shards, from the shard entries when they all record it."""
        entries = [self.manifest.entry(url) for url in self.urls]
        if entries and all(e is not None and key in e for e in entries):
            return sum(e[key] for e in entries)
        return int(self.manifest.data.get(total, 0))

    @property
    def clips(self) -> int:
        return self._recorded("clips", "num_clips")

    @property
    def frames(self) -> int:
        return self._recorded("frames", "num_frames")

    @property
    def hours(self) -> float:
        return self.frames / self.manifest["fps"] / 3600

    @property
    def mean_frames(self) -> float:
        """The set's mean clip length (the whole set's, from its manifest): sliding windows visit a
        clip T / mean_frames times on average."""
        m = self.manifest
        return m.data.get("num_frames", 0) / max(1, m.data.get("num_clips", 1))


def mixture_entries(train, what: str = "data.train") -> list[tuple[str, float | None]]:
    """``data.train`` as (location, weight or None) pairs; a one-line error for anything else."""
    if isinstance(train, (str, Path)):
        train = [train]
    if not isinstance(train, (list, tuple)) or not train:
        raise UsageError(f"{what}: give a shard set (a directory or URL), a list of them, or a list of "
                         f"{ENTRY_FORM}, got {train!r}")
    entries = []
    for i, entry in enumerate(train):
        where = f"{what}[{i}]"
        if isinstance(entry, (str, Path)):
            path, weight = str(entry), None
        elif isinstance(entry, Mapping):
            if unknown := [k for k in entry if k not in ENTRY_KEYS]:
                raise UsageError(f"{where}: unknown key {unknown[0]!r}; a set is {ENTRY_FORM}")
            path, weight = entry.get("path"), entry.get("weight")
            if not isinstance(path, (str, Path)) or not str(path):
                raise UsageError(f"{where}: 'path' must name the set's directory or URL, got {path!r}")
            if weight is not None and (isinstance(weight, bool) or not isinstance(weight, (int, float))
                                       or not math.isfinite(weight) or weight <= 0):
                raise UsageError(f"{where} ({path}): 'weight' must be a positive number, got {weight!r}; "
                                 "leave a set out instead of giving it weight 0")
            path, weight = str(path), None if weight is None else float(weight)
        else:
            raise UsageError(f"{where}: expected a directory or URL or {ENTRY_FORM}, got {entry!r}")
        if not path.strip():
            raise UsageError(f"{where}: empty path")
        entries.append((path, weight))
    weighted = [w is not None for _, w in entries]
    if any(weighted) and not all(weighted):
        unweighted = entries[weighted.index(False)][0]
        raise UsageError(f"{what}: {unweighted} has no weight; give every set a weight, or none "
                         "(then sets are mixed in proportion to their frames)")
    return entries


def open_set(location: str, weight: float | None = None) -> ShardSet:
    """Resolve one location (see the module docstring) to its manifest and shard URLs."""
    import braceexpand

    local = _is_local(location)
    is_set = (Path(location).is_dir() or Path(location).name == MANIFEST) if local else (
        "{" not in location and not url_file_name(location).endswith((".tar", ".tgz", ".tar.gz")))
    if is_set:
        manifest = Manifest.load(location if local else manifest_url(location))
        urls = manifest.shard_urls
    else:  # a pattern of shard files or URLs; the manifest lies beside the first
        urls = list(braceexpand.braceexpand(location))
        first = urls[0]
        if local and not Path(first).exists():
            raise UsageError(f"shards {location!r}: no such directory or file; "
                             "build them with `omg shards build` or `omg shards synth`")
        manifest = Manifest.load(Path(first).parent if local else sibling_url(first, url_file_name(first), MANIFEST))
    urls = sorted(urls)
    return ShardSet(location, manifest, urls, {url: manifest.expected(url) for url in urls}, weight)


def set_sums(shard_set: ShardSet) -> FeatureStats:
    """A set's raw per-feature sums; from its mean/std for manifests written before sums were
    recorded, where that is exact (see the module docstring), else a one-line error."""
    m = shard_set.manifest
    sums = m.sums
    if sums is None:
        rep = representation_of(m)
        exact = type(rep).finalize_stats is Representation.finalize_stats and m.data.get("stats_origin") != "source"
        if not exact or not m.data.get("num_frames"):
            why = ("a published normalisation" if m.data.get("stats_origin") == "source" else
                   f"{m['representation']} finalizes its std" if not exact else "no frame count")
            raise UsageError(f"shard set {shard_set.location}: its manifest has no 'sums' (built by an older omg) and "
                             f"its mean/std ({why}) cannot be pooled; rebuild it with `omg shards build`, "
                             "or train on it alone")
        n = int(m["num_frames"])
        mean, std = m.mean.astype(np.float64), m.std.astype(np.float64)
        sums = FeatureStats(n, mean * n, (std * std + mean * mean) * n)
        log.info("shard set %s: no raw sums in its manifest; pooled from its mean/std", shard_set.location)
    if sums.count <= 0:
        raise UsageError(f"shard set {shard_set.location}: its manifest's sums cover no frames; rebuild it")
    return sums


def representation_of(manifest: Manifest) -> Representation:
    return get_representation(manifest["representation"], get_skeleton(manifest["skeleton"]))


def pooled_stats(sets: list[ShardSet], shares: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The mixture's (mean, std), each (D,): the sets' per-frame moments weighted by their shares,
    finalized once by the representation."""
    mean = second = 0.0
    for shard_set, share in zip(sets, shares):
        sums = set_sums(shard_set)
        mean = mean + share * sums.total / sums.count
        second = second + share * sums.total_sq / sums.count
    std = np.sqrt(np.maximum(second - mean * mean, 0.0))
    return representation_of(sets[0].manifest).finalize_stats(mean, std)


@dataclass
class Mixture:
    """The shard sets of ``data.train`` and the share of samples each gets."""

    sets: list[ShardSet]
    shares: list[float]  # sum to 1, in the order of ``sets``
    what: str = "data.train"

    @property
    def manifest(self) -> Manifest:
        """The first set's manifest (every set agrees on representation, skeleton, fps, features)."""
        return self.sets[0].manifest

    @property
    def urls(self) -> list[str]:
        return sorted(url for s in self.sets for url in s.urls)

    @property
    def checks(self) -> dict[str, dict]:
        return {url: expected for s in self.sets for url, expected in s.checks.items()}

    @property
    def frame_shares(self) -> list[float]:
        """Each set's share of the frames: the shares of a concatenation."""
        frames = [s.frames for s in self.sets]
        total = sum(frames)
        return [f / total if total else 1 / len(frames) for f in frames]

    def spec(self) -> DataSpec:
        """The data spec models store: a single set's manifest spec, or the mixture's pooled stats."""
        if len(self.sets) == 1:
            return self.manifest.spec()
        sourced = [s.location for s in self.sets if s.manifest.data.get("stats_origin") == "source"]
        if sourced:
            log.info("published normalisation of %s replaced by the mixture's pooled statistics", ", ".join(sourced))
        mean, std = pooled_stats(self.sets, self.shares)
        return DataSpec.coerce({**self.manifest.data, "mean": mean.tolist(), "std": std.tolist()},
                               f"the mixture of {self.what}")

    def describe(self) -> list[str]:
        """One line per set (clips, frames, hours, weight, share of samples, and how much more or less
        often than in a concatenation its frames are seen), and a total line."""
        lines = []
        for s, share, frame_share in zip(self.sets, self.shares, self.frame_shares):
            weight = "by frames" if s.weight is None else f"weight {s.weight:g}"
            over = share / frame_share if frame_share else float("inf")
            lines.append(f"{s.location}: {s.clips} clips, {s.frames} frames, {s.hours:.2f} h; {weight}, "
                         f"share {100 * share:.1f}% of samples ({over:.2f}x its share of the frames)")
        fps = self.manifest["fps"]
        frames = sum(s.frames for s in self.sets)
        stats = "the set's own" if len(self.sets) == 1 else "pooled from the sets' sums by share"
        lines.append(f"mixture: {len(self.sets)} sets, {sum(s.clips for s in self.sets)} clips, {frames} frames, "
                     f"{frames / fps / 3600:.2f} h at {fps:g} fps; normalisation {stats}")
        return lines


def load_mixture(train, what: str = "data.train") -> Mixture:
    """``data.train`` (a location, a list of them, or a list of ``{path, weight}``) as a ``Mixture``.

    Unweighted locations that resolve to one manifest (patterns of one set) are one set. Every set
    must agree with the first on what ``DataSpec.check_compatible`` requires (representation,
    skeleton, features, fps), else a one-line error names the set and the field."""
    sets: list[ShardSet] = []
    for i, (location, weight) in enumerate(mixture_entries(train, what)):
        shard_set = open_set(location, weight)
        twin = next((s for s in sets if s.manifest.location == shard_set.manifest.location), None)
        if twin is not None and weight is None:
            twin.urls = sorted(set(twin.urls) | set(shard_set.urls))
            twin.checks.update(shard_set.checks)
            continue
        if twin is not None:
            raise UsageError(f"{what}[{i}] ({location}): the set {shard_set.manifest.location} is listed twice; "
                             "give it once with the sum of the weights")
        if sets:
            sets[0].manifest.spec().check_compatible(
                shard_set.manifest.spec(), f"{what}[0] ({sets[0].location})", f"{what}[{i}] ({location})",
                "a mixture's sets must be built with the same --representation, --skeleton and --fps")
        sets.append(shard_set)
    if sets[0].weight is None:
        frames = [s.frames for s in sets]
        shares = [f / sum(frames) for f in frames] if sum(frames) else [1 / len(sets)] * len(sets)
    else:
        total = sum(s.weight for s in sets)
        shares = [s.weight / total for s in sets]
    return Mixture(sets, shares, what)
