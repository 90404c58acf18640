"""Shard writer (atomic, resumable, counted skips), manifest, and validation."""

from __future__ import annotations

import hashlib
import io
import json

import numpy as np
import pytest

from helpers import JointPositions, rewrite_member, toy_clip, write_toy_shards
from omg.data.shards import BUILD_STATE, MANIFEST, SCHEMA_VERSION, Manifest, ShardWriter, iter_tar, validate
from omg.motion import Clip
from omg.skeleton import SMPL22


def test_written_shards_hold_every_clip_with_manifest_stats(tmp_path):
    out = write_toy_shards(tmp_path / "s", num_clips=23, max_clips=5)
    m = Manifest.load(out)
    assert m["schema_version"] == SCHEMA_VERSION
    assert ((m["num_clips"], m["num_shards"], m["representation"], m["skeleton"], m["fps"])
            == (23, 5, "test-positions", "smpl22", 20.0))
    clips = [toy_clip(i) for i in range(23)]
    frames = np.concatenate([c.positions.reshape(len(c), -1) for c in clips]).astype(np.float64)
    assert m["num_frames"] == len(frames)
    np.testing.assert_allclose(m.mean, frames.mean(0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(m.std, np.maximum(frames.std(0), 1e-4), rtol=1e-4, atol=1e-5)
    samples = [s for p in m.shard_paths for s in iter_tar(p)]
    assert [s["__key__"] for s in samples] == [f"clip_{i:04d}" for i in range(23)]  # dots removed
    first = samples[0]
    np.testing.assert_array_equal(np.load(io.BytesIO(first["motion.npy"])),
                                  clips[0].positions.reshape(len(clips[0]), -1))
    meta = json.loads(first["meta.json"])
    assert meta["id"] == "clip.0000" and meta["skeleton"] == "smpl22" and meta["category"] == "human"
    assert json.loads(first["texts.json"]) == ["caption 0"]
    assert not (out / BUILD_STATE).exists()
    # per shard the manifest records what a reader checks: sample count, byte size, sha256
    for entry, path in zip(m["shards"], m.shard_paths):
        data = path.read_bytes()
        assert m.expected(path) == {"samples": entry["clips"], "size": len(data),
                                    "sha256": hashlib.sha256(data).hexdigest()}
        assert len(list(iter_tar(path, **m.expected(path), whole=True))) == entry["clips"]
    assert [e["clips"] for e in m["shards"]] == [5, 5, 5, 5, 3]


def test_bad_clips_are_skipped_and_counted(tmp_path):
    nan = toy_clip(1)
    nan.positions[3, 2, 1] = np.nan
    empty = Clip(id="empty", skeleton=SMPL22, fps=20.0, positions=np.zeros((0, 22, 3), np.float32))
    items = [toy_clip(0), nan, empty, toy_clip(0), OSError("bad.bvh: truncated"), toy_clip(2)]
    summary = ShardWriter(tmp_path, JointPositions(SMPL22), fps=20.0, log=lambda m: None).write(items)
    assert summary.clips == 2 and sum(summary.skipped.values()) == 4
    assert Manifest.load(tmp_path)["skipped"] == summary.skipped
    assert "skipped 4" in str(summary)


class Interrupt(Exception):
    pass


def _source(n, crash_at=None, consumed=None):
    for i in range(n):
        if i == crash_at:
            raise Interrupt
        if consumed is not None:
            consumed.append(i)
        yield toy_clip(i)


def test_interrupted_build_resumes_without_redoing_finished_shards(tmp_path):
    rep = JointPositions(SMPL22)
    ShardWriter(tmp_path / "whole", rep, 20.0, max_clips=4, log=lambda m: None).write(_source(30))

    out = tmp_path / "resumed"
    with pytest.raises(Interrupt):
        ShardWriter(out, rep, 20.0, max_clips=4, log=lambda m: None).write(_source(30, crash_at=14))
    assert sorted(p.name for p in out.glob("shard-*.tar")) == [f"shard-{i:06d}.tar" for i in range(3)]
    assert (out / BUILD_STATE).exists() and not (out / MANIFEST).exists()
    with pytest.raises(Exception, match="unfinished build"):
        Manifest.load(out)

    consumed = []
    summary = ShardWriter(out, rep, 20.0, max_clips=4, log=lambda m: None).write(_source(30, consumed=consumed))
    assert summary.resumed_shards == 3 and summary.clips == 30
    assert consumed[0] == 0 and len(consumed) == 30  # the source is replayed, but finished clips are not re-encoded
    for name in (f"shard-{i:06d}.tar" for i in range(8)):
        assert (out / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()
    assert (json.loads((out / MANIFEST).read_text())["mean"]
            == json.loads((tmp_path / "whole" / MANIFEST).read_text())["mean"])


def test_resume_with_other_settings_is_refused(tmp_path):
    with pytest.raises(Interrupt):
        ShardWriter(tmp_path, JointPositions(SMPL22), 20.0, max_clips=2,
                    log=lambda m: None).write(_source(10, crash_at=5))
    with pytest.raises(Exception, match="unfinished build"):
        ShardWriter(tmp_path, JointPositions(SMPL22), 30.0, max_clips=2, log=lambda m: None).write(_source(10))


def test_validate_names_bad_samples_by_shard_and_key(toy_shards):
    m = Manifest.load(toy_shards)
    rewrite_member(m.shard_paths[1], "clip_0006.motion.npy", b"garbage")
    truncated = m.shard_paths[3]
    truncated.write_bytes(truncated.read_bytes()[:1500])
    _, good, problems = validate(toy_shards)
    assert any(p.startswith("shard-000001.tar clip_0006:") for p in problems)
    assert any(p.startswith("shard-000001.tar: size check failed: truncated: ") for p in problems)  # rewritten shard
    assert any(p.startswith("shard-000003.tar: readable check failed: unreadable after 0 samples") for p in problems)
    assert good == 30  # only samples of shards that pass every check


def test_inspect_command_exit_codes(toy_shards, capsys):
    from omg.tools.shards import main as shards_main

    shards_main(["inspect", str(toy_shards)])
    out = capsys.readouterr().out
    assert "40 clips" in out and "40 valid samples, 0 problems" in out
    rewrite_member(Manifest.load(toy_shards).shard_paths[0], "clip_0001.meta.json", b"{}")
    with pytest.raises(SystemExit) as e:
        shards_main(["inspect", str(toy_shards)])
    assert e.value.code == 1
    assert "BAD shard-000000.tar clip_0001: meta.json lacks id" in capsys.readouterr().out
