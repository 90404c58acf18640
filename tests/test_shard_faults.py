"""Real corruptions of a shard set, written by the tests: garbled bytes inside a sample, a tar
cut at a header boundary or inside a member, an invalid manifest. Each is caught when reading
(``iter_tar`` with the manifest's expectations, ``ShardError``), by ``omg shards inspect``
(one error line naming the shard and the check, exit 1) or when loading the manifest
(``UsageError``, exit 2), never by a traceback."""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import tarfile

import numpy as np
import pytest

from helpers import write_toy_shards
from omg.cli import main
from omg.data.shards import MANIFEST, Manifest, ShardError, check_shards, iter_tar, verify_shard
from omg.errors import UsageError


@pytest.fixture(scope="session")
def pristine(tmp_path_factory):
    """8 shards of 5 clips, written once; each test corrupts its own copy."""
    return write_toy_shards(tmp_path_factory.mktemp("pristine") / "toy", num_clips=40, max_clips=5)


@pytest.fixture
def shards(pristine, tmp_path):
    out = tmp_path / "toy"
    out.mkdir()
    for f in pristine.iterdir():
        (out / f.name).write_bytes(f.read_bytes())
    return out


def _members(path):
    with tarfile.open(path) as tar:
        return tar.getmembers()


def flip_npy_bytes(path, member_index: int = 3) -> None:
    """XOR one low mantissa byte of a float in a sample's motion.npy: the tar stays valid, the
    array still decodes to finite numbers, only the sha256 can tell."""
    member = [m for m in _members(path) if m.name.endswith(".motion.npy")][member_index]
    data = bytearray(path.read_bytes())
    at = member.offset_data + 128 + 4 * 7  # past the npy header, the low byte of float 7
    data[at] ^= 0x01
    path.write_bytes(bytes(data))


def cut_at_header(path, sample_index: int = 2) -> int:
    """Truncate the tar at the 512-byte header of a sample's first member; tarfile reads the rest
    as a clean, shorter archive."""
    member = [m for m in _members(path) if m.name.endswith(".motion.npy")][sample_index]
    assert member.offset % 512 == 0
    path.write_bytes(path.read_bytes()[: member.offset])
    return member.offset


def cut_mid_member(path, sample_index: int = 2) -> None:
    member = [m for m in _members(path) if m.name.endswith(".motion.npy")][sample_index]
    path.write_bytes(path.read_bytes()[: member.offset_data + member.size // 2])


def inspect(shard_dir, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(["shards", "inspect", str(shard_dir)])
    out, err = capsys.readouterr()
    return e.value.code, out, err


def _assert_one_error_line(err: str, *needles: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("omg: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# --- garbled bytes --------------------------------------------------------------------------


def test_garbled_sample_fails_sha256_when_streamed_and_is_never_yielded_when_read_whole(shards):
    m = Manifest.load(shards)
    path = m.shard_paths[2]
    flip_npy_bytes(path)
    expected = m.expected(path)
    assert set(expected) == {"sha256", "samples", "size"}

    seen = []
    with pytest.raises(ShardError) as e:
        for raw in iter_tar(path, **expected):
            seen.append(raw["__key__"])
    assert len(seen) == 5  # streamed: the check comes at the end of the shard
    assert e.value.check == "sha256" and e.value.shard == str(path)
    assert str(e.value).startswith(f"{path}: sha256 ") and "garbled" in str(e.value)

    seen = []
    with pytest.raises(ShardError, match="sha256") as e:
        for raw in iter_tar(path, **expected, whole=True):
            seen.append(raw)
    assert seen == [] and e.value.check == "sha256"

    with pytest.raises(ShardError, match="sha256"):
        verify_shard(path, expected["sha256"], size=expected["size"])
    assert verify_shard(m.shard_paths[0], **{"sha256": m.expected(m.shard_paths[0])["sha256"]})
    # the other shards pass every check, in both modes
    for p in m.shard_paths[:2]:
        assert len(list(iter_tar(p, **m.expected(p)))) == len(list(iter_tar(p, **m.expected(p), whole=True))) == 5


def test_inspect_reports_a_garbled_shard(shards, capsys):
    flip_npy_bytes(Manifest.load(shards).shard_paths[2])
    code, out, err = inspect(shards, capsys)
    assert code == 1
    assert "BAD shard-000002.tar: sha256 check failed: sha256 " in out
    assert "7 of 8 shards verified against the manifest, 1 failed (shard-000002.tar: sha256)" in out
    assert "35 valid samples" in out  # the garbled shard's samples are not counted as valid
    _assert_one_error_line(err, str(shards), "1 of 8 shards failed verification", "shard-000002.tar", "sha256")


def test_sha256_error_pickles_with_its_fields():
    e = pickle.loads(pickle.dumps(ShardError("/d/shard-000001.tar", "sha256", "sha256 abc… does not match")))
    assert (e.shard, e.check, e.reason) == ("/d/shard-000001.tar", "sha256", "sha256 abc… does not match")
    assert str(e) == "/d/shard-000001.tar: sha256 abc… does not match" and isinstance(e, ValueError)


# --- truncation -----------------------------------------------------------------------------


def test_tar_cut_at_a_header_boundary_is_detected_by_every_signal(shards):
    m = Manifest.load(shards)
    path = m.shard_paths[1]
    expected = m.expected(path)
    cut = cut_at_header(path)
    with tarfile.open(path) as tar:  # the fault this guards against: tarfile sees a clean, short archive
        assert len(tar.getmembers()) == 6

    with pytest.raises(ShardError, match=f"truncated: {cut} of {expected['size']} bytes") as e:
        next(iter_tar(path, **expected))  # a local file's size is checked before the first sample
    assert e.value.check == "size"

    keys = []
    with pytest.raises(ShardError, match="truncated: 2 of 5 samples") as e:
        for raw in iter_tar(path, samples=5):  # e.g. a remote shard: counted as it streams
            keys.append(raw["__key__"])
    assert e.value.check == "samples" and keys == ["clip_0005", "clip_0006"]
    with pytest.raises(ShardError, match="truncated: 2 of 5 samples"):
        list(iter_tar(path, samples=5, whole=True))

    with pytest.raises(ShardError, match="no end-of-archive blocks") as e:
        list(iter_tar(path))  # no expectations at all: the missing end blocks still tell
    assert e.value.check == "end-of-archive"


def test_tar_cut_inside_a_member(shards, capsys):
    m = Manifest.load(shards)
    path = m.shard_paths[4]
    cut_mid_member(path)
    with pytest.raises(ShardError, match="truncated: ") as e:
        next(iter_tar(path, **m.expected(path)))
    assert e.value.check == "size"
    with pytest.raises(ShardError, match=r"unreadable after 1 sample \(ReadError: unexpected end of data\)$") as e:
        list(iter_tar(path))  # webdataset holds a sample back until the next key starts: sample 1 is lost too
    assert e.value.check == "readable"

    code, out, err = inspect(shards, capsys)
    assert code == 1
    assert ("BAD shard-000004.tar: readable check failed: "
            "unreadable after 1 sample (ReadError: unexpected end of data); truncated: " in out)
    _assert_one_error_line(err, "1 of 8 shards failed verification", "shard-000004.tar", "readable")


def test_inspect_reports_a_header_boundary_cut_and_a_missing_shard(shards, capsys):
    m = Manifest.load(shards)
    cut_at_header(m.shard_paths[1])
    m.shard_paths[6].unlink()
    code, out, err = inspect(shards, capsys)
    assert code == 1
    assert "BAD shard-000001.tar: samples check failed: truncated: 2 of 5 samples" in out
    assert "BAD shard-000006.tar: file check failed: no such file" in out
    assert ("6 of 8 shards verified against the manifest, 2 failed "
            "(shard-000001.tar: samples, shard-000006.tar: file)" in out)
    _assert_one_error_line(err, "2 of 8 shards failed verification", "shard-000001.tar")


def test_inspect_names_a_fifo_or_folder_named_like_a_shard(shards, capsys):
    """Not "no such file": the name is there, but it is no file to read (and a FIFO would block the read)."""
    m = Manifest.load(shards)
    m.shard_paths[2].unlink()
    os.mkfifo(m.shard_paths[2])
    m.shard_paths[5].unlink()
    m.shard_paths[5].mkdir()
    code, out, err = inspect(shards, capsys)
    assert code == 1
    assert "BAD shard-000002.tar: file check failed: not a regular file (a FIFO, socket or device)" in out
    assert "BAD shard-000005.tar: file check failed: is a directory; a file is expected" in out
    _assert_one_error_line(err, "2 of 8 shards failed verification", "shard-000002.tar")


def test_inspect_reports_a_bad_sample_once(shards, capsys, caplog):
    """A sample that does not decode, in a shard that passes every check: one BAD line and the count,
    not a warning at every visit of the batch-composition draws (there were over 20 of them)."""
    path = Manifest.load(shards).shard_paths[3]
    with tarfile.open(path) as tar:
        members = [(m, tar.extractfile(m).read()) for m in tar.getmembers()]
    victim = next(m.name for m, _ in members if m.name.endswith(".motion.npy"))
    narrow = io.BytesIO()
    np.save(narrow, np.zeros((8, 2), np.float32))  # the manifest's feature width is not 2
    with tarfile.open(path, "w") as tar:
        for m, data in members:
            data = narrow.getvalue() if m.name == victim else data
            m.size = len(data)
            tar.addfile(m, io.BytesIO(data))
    _edit_manifest(shards, lambda d: d["shards"][3].update(bytes=path.stat().st_size,
                                                          sha256=hashlib.sha256(path.read_bytes()).hexdigest()))
    key = victim.split(".")[0]
    code, out, err = inspect(shards, capsys)
    assert code == 1
    assert out.count(key) == 1 and "39 valid samples, 1 problems" in out
    assert [r.getMessage() for r in caplog.records if key in r.getMessage()] == []
    _assert_one_error_line(err, "1 bad samples", key)


def test_tar_with_garbage_after_a_damaged_header_is_not_a_clean_end(tmp_path):
    """tarfile also ends quietly at a zeroed member header; what follows is not end-of-archive zeros."""
    out = write_toy_shards(tmp_path / "one", num_clips=40, max_clips=40)
    path = Manifest.load(out).shard_paths[0]
    member = [m for m in _members(path) if m.name.endswith(".motion.npy")][3]
    data = bytearray(path.read_bytes())
    data[member.offset : member.offset + 512] = bytes(512)
    path.write_bytes(bytes(data))
    with pytest.raises(ShardError, match="early end of the archive") as e:
        list(iter_tar(path))
    assert e.value.check == "end-of-archive"


# --- the manifest ---------------------------------------------------------------------------


def _edit_manifest(shard_dir, edit) -> None:
    path = shard_dir / MANIFEST
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def test_invalid_manifest_json_is_one_usage_line(shards, capsys):
    (shards / MANIFEST).write_text('{"schema_version": 1, "shards": [')
    code, out, err = inspect(shards, capsys)
    assert code == 2
    _assert_one_error_line(err, str(shards / MANIFEST), "not valid JSON", "line 1")


def test_manifest_missing_a_key_is_one_usage_line(shards, capsys):
    _edit_manifest(shards, lambda d: d.pop("feature_dim"))
    code, out, err = inspect(shards, capsys)
    assert code == 2
    _assert_one_error_line(err, str(shards / MANIFEST), "missing key 'feature_dim'")


def _set(key, value):
    return lambda d: d.__setitem__(key, value)


def _set_shard(key, value):
    return lambda d: d["shards"][0].__setitem__(key, value)


@pytest.mark.parametrize(
    "edit, message",
    [
        (_set("schema_version", 2), "schema version 2, this omg reads 1"),
        (lambda d: d.pop("schema_version"), "missing key 'schema_version'"),
        (lambda d: [d.pop("mean"), d.pop("std")], "missing keys 'mean', 'std'"),
        (_set("feature_dim", "66"), "'feature_dim' must be a positive integer, got '66'"),
        (_set("fps", None), "'fps' must be a positive number"),
        (_set("mean", [0.0] * 3), "'mean' has 3 values, 'feature_dim' is 66"),
        (_set("std", [0.0] * 66), "'std' must be positive and finite"),
        (_set("shards", {"name": "shard-000000.tar"}), "'shards' must be a non-empty list"),
        (_set("shards", []), "'shards' must be a non-empty list"),
        (_set_shard("name", "../elsewhere.tar"), "shards[0] needs a 'name'"),
        (_set_shard("clips", "5"), "shard shard-000000.tar: 'clips' must be a non-negative integer"),
        (_set_shard("sha256", "abc"), "'sha256' must be 64 lowercase hex digits"),
        (_set("num_shards", 3), "'num_shards' is 3 but 8 shards are listed"),
        (_set("num_clips", 41), "'num_clips' is 41 but the shards hold 40 clips"),
    ],
)
def test_invalid_manifest_values_are_usage_errors(shards, edit, message):
    _edit_manifest(shards, edit)
    with pytest.raises(UsageError) as e:
        Manifest.load(shards)
    assert str(e.value).startswith(f"{shards / MANIFEST}: ") and message in str(e.value)
    assert "\n" not in str(e.value)


def test_manifest_that_is_no_object_or_no_text(shards):
    (shards / MANIFEST).write_text("[1, 2]")
    with pytest.raises(UsageError, match="not a JSON object but a JSON list"):
        Manifest.load(shards)
    (shards / MANIFEST).write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(UsageError, match="not a text file|not valid JSON"):
        Manifest.load(shards)


def test_old_manifest_without_sizes_and_hashes_stays_readable(shards, capsys):
    def strip(d):
        for entry in d["shards"]:
            del entry["bytes"], entry["sha256"], entry["frames"]
        del d["num_frames"], d["num_shards"], d["command"]

    _edit_manifest(shards, strip)
    m = Manifest.load(shards)
    assert m.expected(m.shard_paths[0]) == {"samples": 5} and m.expected("elsewhere/shard-999999.tar") == {}
    assert "40 clips" in m.summary()
    result = check_shards(shards)
    assert result.good == 40 and not result.problems and result.verified == 0
    main(["shards", "inspect", str(shards)])
    out, err = capsys.readouterr()
    assert "0 of 8 shards verified against the manifest, 8 without a sha256 in the manifest; 40 valid samples" in out
    assert err == ""
