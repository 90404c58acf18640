"""Reading shards checked against their manifest in the same single pass that parses them
(``iter_tar``), and the whole-set check of ``omg shards inspect`` (``check_shards``)."""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from omg.data.deadline import deadline
from omg.data.shards.manifest import Manifest
from omg.data.shards.remote import _abandon, _local_path, open_url
from omg.data.shards.schema import _COMPRESSED_MAGIC, _END_OF_ARCHIVE, ShardError, decode_sample
from omg.files import file_problem


class _CheckedReader:
    """A read-only stream wrapper that hashes and counts the bytes as they pass and keeps the
    first and the last bytes, so a shard is verified in the same single pass that parses it."""

    def __init__(self, raw, sha256: bool):
        self.raw = raw
        self.hash = hashlib.sha256() if sha256 else None
        self.count = 0
        self.head = self.tail = b""
        self.trailing_garbage = False  # non-zero bytes drained after tarfile stopped reading

    def read(self, size: int = -1) -> bytes:
        data = self.raw.read(size)
        if data:
            if self.hash is not None:
                self.hash.update(data)
            self.count += len(data)
            if len(self.head) < 8:
                self.head = (self.head + data)[:8]
            self.tail = data[-1024:] if len(data) >= 1024 else (self.tail + data)[-1024:]
        return data

    def drain(self) -> None:
        """Read the rest: what follows the point where tarfile stopped (its read-ahead aside)
        must be end-of-archive zeros, else a damaged header ended the archive early."""
        while data := self.read(1 << 20):
            if data.count(0) != len(data):
                self.trailing_garbage = True

    @property
    def compressed(self) -> bool:
        return self.head.startswith(_COMPRESSED_MAGIC)


def _first_arg(e: Exception) -> str:
    """An exception's own message, without the " @ <stream>" webdataset appends."""
    return str(e.args[0]).split(" @ <")[0] if e.args else type(e).__name__


def _size_error(url: str, found: int, size: int) -> ShardError:
    if found < size:
        return ShardError(url, "size", f"truncated: {found} of {size} bytes")
    return ShardError(url, "size", f"{found} bytes, the manifest says {size}")


def _byte_errors(url: str, reader: _CheckedReader, sha256: str | None, size: int | None,
                 early_end: bool = False) -> list[ShardError]:
    """Checks on the bytes of a fully read shard, most telling first; ``early_end``: non-zero
    bytes followed the point where tarfile saw the end of the archive."""
    errors = []
    if size is not None and reader.count != size:
        errors.append(_size_error(url, reader.count, size))
    if not reader.compressed and (reader.count < len(_END_OF_ARCHIVE) or reader.tail != _END_OF_ARCHIVE):
        errors.append(ShardError(url, "end-of-archive",
                                 f"no end-of-archive blocks: the tar is cut after {reader.count} bytes"))
    elif early_end:
        errors.append(ShardError(url, "end-of-archive",
                                 "data after an early end of the archive (a damaged member header?)"))
    if sha256 is not None and reader.hash is not None and (digest := reader.hash.hexdigest()) != sha256:
        errors.append(ShardError(url, "sha256", f"sha256 {digest[:12]}… of its {reader.count} bytes does not match "
                                                f"the manifest's {sha256[:12]}… (garbled or replaced)"))
    return errors


def _count_error(url: str, count: int, samples: int | None) -> ShardError | None:
    if samples is None or count == samples:
        return None
    if count < samples:
        return ShardError(url, "samples", f"truncated: {count} of {samples} samples")
    return ShardError(url, "samples", f"{count} samples, the manifest says {samples}")


def _tar_samples(stream, url: str) -> Iterator[dict[str, bytes]]:
    import webdataset as wds

    files = wds.tariterators.tar_file_expander([{"url": url, "stream": stream}])
    for sample in wds.tariterators.group_by_keys(files):
        sample.pop("__url__", None)
        yield sample


def _read_shard(url: str, sha256: str | None = None, samples: int | None = None, size: int | None = None,
                whole: bool = False, precheck: bool = True) -> Iterator[dict[str, bytes]]:
    local = _local_path(url)
    if local is not None:
        if problem := file_problem(local):  # a FIFO would block the read
            raise ShardError(url, "file", problem)
        if precheck and size is not None and (found := local.stat().st_size) != size:
            raise _size_error(url, found, size)
    try:
        raw = open_url(url)
    except OSError as e:
        raise ShardError(url, "file", f"cannot be opened ({e.strerror or e})") from None
    source = _CheckedReader(raw, sha256 is not None)  # hashes, counts and keeps the tail of the file's bytes
    try:
        if whole:  # parsed from memory: every check runs before the first sample is yielded
            data = b"".join(iter(lambda: source.read(1 << 22), b""))
            reader = _CheckedReader(io.BytesIO(data), False)
            del data
        else:
            reader = source
        count, buffered, parsed = 0, [], _tar_samples(reader, url)
        while True:
            try:
                sample = next(parsed)
            except StopIteration:
                break
            except Exception as e:  # noqa: BLE001 - any failure to parse the tar names the shard
                reason = (f"unreadable after {count} sample{'' if count == 1 else 's'} "
                          f"({type(e).__name__}: {_first_arg(e)})")
                source.drain()
                if notes := [err.reason for err in _byte_errors(url, source, sha256, size)
                             if err.check != "end-of-archive"]:
                    reason += "; " + "; ".join(notes)
                raise ShardError(url, "readable", reason) from None
            count += 1
            if whole:
                buffered.append(sample)
            else:
                yield sample
        reader.drain()
        errors = _byte_errors(url, source, sha256, size, early_end=reader.trailing_garbage)
        if error := _count_error(url, count, samples):
            errors.insert(0, error)
        if errors:
            raise errors[0]
        yield from buffered
    except BaseException:  # a failed check, a stall (omg.data.deadline), or a reader that stopped early
        _abandon(raw)
        raise
    else:
        raw.close()


def iter_tar(path: str | Path, sha256: str | None = None, *, samples: int | None = None, size: int | None = None,
             whole: bool = False) -> Iterator[dict[str, bytes]]:
    """Raw samples (``{"__key__", ext: bytes}``) of one tar, grouped by key like WebDataset.

    ``path`` is a file or any URL ``open_url`` opens (``pipe:`` commands, object-store URLs
    through fsspec, what ``webdataset.gopen`` opens). The expected values come from
    the manifest (``Manifest.expected(url)`` gives them as keyword arguments):

    - ``sha256``: the bytes are hashed as they are read;
    - ``samples``: the number of samples the shard must yield ("truncated: N of M samples");
    - ``size``: the file size in bytes; a local file is measured before anything is read.

    A tar without its end-of-archive zero blocks (cut at a member boundary) fails whether
    or not anything is expected. Any failure raises ``ShardError`` naming the shard and the
    check. Streaming (``whole=False``) yields samples as they are read, so the count, hash and
    end checks raise only after the shard's last sample: the samples before cannot be taken
    back. ``whole=True`` reads the shard into memory and runs every check before yielding
    the first sample: nothing from a bad shard is ever yielded.
    """
    return _read_shard(str(path), sha256, samples, size, whole, precheck=True)


def verify_shard(path: str | Path, sha256: str | None = None, *, size: int | None = None) -> str:
    """Hash a whole shard file (in chunks, without parsing it); raises ``ShardError`` when it is
    missing or its size or sha256 differ from the expected ones; returns its sha256."""
    url = str(path)
    local = _local_path(url)
    if local is None or (problem := file_problem(local)):
        raise ShardError(url, "file", problem if local is not None else "no such file")
    if size is not None and (found := local.stat().st_size) != size:
        raise _size_error(url, found, size)
    digest = hashlib.sha256()
    with open(local, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    if sha256 is not None and digest.hexdigest() != sha256:
        raise ShardError(url, "sha256", f"sha256 {digest.hexdigest()[:12]}… does not match the manifest's "
                                        f"{sha256[:12]}… (garbled or replaced)")
    return digest.hexdigest()


@dataclass
class ShardCheck:
    """The result of checking one shard: samples read and decoded, sample-level problems,
    the shard-level ``error`` if any, and which manifest checks could be made."""

    name: str
    samples: int = 0
    good: int = 0
    problems: list[str] = field(default_factory=list)
    error: ShardError | None = None
    checks: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.error is None and not self.problems

    @property
    def verified(self) -> bool:
        """Its bytes matched the manifest's sha256 (and every other recorded check passed)."""
        return self.error is None and "sha256" in self.checks


@dataclass
class ShardSetCheck:
    """The result of ``check_shards``: one ``ShardCheck`` per shard of the manifest."""

    manifest: Manifest
    shards: list[ShardCheck]

    @property
    def good(self) -> int:
        """Samples that decoded, in shards that passed every shard-level check."""
        return sum(s.good for s in self.shards if s.error is None)

    @property
    def failed(self) -> list[ShardCheck]:
        return [s for s in self.shards if s.error is not None]

    @property
    def verified(self) -> int:
        return sum(s.verified for s in self.shards)

    @property
    def problems(self) -> list[str]:
        """Shard-level failures as '<shard>: <check> check failed: <reason>' and bad samples as
        '<shard> <key>: <reason>'."""
        out = []
        for s in self.shards:
            if s.error is not None:
                out.append(f"{s.name}: {s.error.check} check failed: {s.error.reason}")
            out += s.problems
        return out


def check_shards(shard_dir: str | Path, timeout: float = 0.0, timeout_name: str = "timeout") -> ShardSetCheck:
    """Read every shard of a set once: decode every sample and check each shard's file, size,
    sample count, end-of-archive blocks and sha256 against the manifest. Raises
    ``UsageError`` only for a missing or invalid manifest, or a shard whose read takes over ``timeout``
    seconds (0: no limit; ``timeout_name`` is the option that sets it); every other fault is reported."""
    def stalled(url: str) -> str:
        return (f"{url} was not read in {timeout_name}={timeout:g} s: a stalled read; check the storage, "
                f"or raise {timeout_name} (0 waits forever)")

    with deadline(timeout, stalled(f"the manifest of {shard_dir}")):
        manifest = Manifest.load(shard_dir)
    results = []
    for entry, url in zip(manifest["shards"], manifest.shard_urls):
        expected = manifest.expected(entry["name"])
        result = ShardCheck(entry["name"], checks=("file", "readable", "end-of-archive", *expected))
        with deadline(timeout, stalled(url)):
            try:
                # streamed without the size pre-check: a bad shard's samples are still decoded and named
                for raw in _read_shard(url, whole=False, precheck=False, **expected):
                    result.samples += 1
                    try:
                        decode_sample(raw, manifest["feature_dim"])
                        result.good += 1
                    except (ValueError, KeyError) as e:
                        result.problems.append(f"{entry['name']} {raw.get('__key__')}: {e}")
            except ShardError as e:
                result.error = e
        results.append(result)
    return ShardSetCheck(manifest, results)


def validate(shard_dir: str | Path) -> tuple[Manifest, int, list[str]]:
    """Decode every sample and check every shard against the manifest (see ``check_shards``);
    returns (manifest, good sample count, problems as 'shard key: reason' or 'shard: ...')."""
    result = check_shards(shard_dir)
    return result.manifest, result.good, result.problems
