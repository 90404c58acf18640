"""Builds at scale: --workers N gives the shards --workers 1 gives, --part i --parts n plus
``omg shards merge`` gives the clips and statistics of one build, an interrupted parallel build
resumes, and a build reports its progress while it runs."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from helpers.lazy_walks import SOURCE
from helpers.lazy_walks import build as _build
from omg.cli import main
from omg.data.shards import BUILD_STATE, BuildProgress, Manifest, decode_sample, iter_tar, merge_shard_sets
from omg.errors import UsageError
from omg.tools.shards import build

pytestmark = pytest.mark.xdist_group("build_scale")  # the tests share the `one_worker` fixture's build


def _set(shard_dir: Path) -> dict:
    """What a set holds: manifest (less its command), shard bytes by name."""
    manifest = json.loads((shard_dir / "manifest.json").read_text())
    manifest.pop("command")
    return {"manifest": manifest, "shards": {p.name: p.read_bytes() for p in sorted(shard_dir.glob("shard-*.tar"))}}


def _clips(shard_dir: Path) -> dict[str, np.ndarray]:
    manifest = Manifest.load(shard_dir)
    return {s["meta"]["id"]: s["motion"] for path in manifest.shard_paths
            for s in map(decode_sample, iter_tar(path, **manifest.expected(path)))}


@pytest.fixture(scope="session")
def one_worker(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scale") / "w1"
    _build(out, workers=1)
    return out


def test_workers_give_the_same_shards(one_worker, tmp_path):
    readers = tmp_path / "readers"
    readers.mkdir()
    summaries = _build(tmp_path / "w3", workers=3, options={"delay": 0.1, "readers": str(readers)})
    assert len(list(readers.iterdir())) >= 2  # the helpers did read items
    assert [s.resumed_shards for s in summaries] == [0, 0]
    for split in ("train", "val"):
        assert _set(tmp_path / "w3" / split) == _set(one_worker / split)
    train, val = (json.loads((one_worker / split / "manifest.json").read_text()) for split in ("train", "val"))
    # 48 items: 4 bad (i % 11 == 5), 4 of another domain (i % 13 == 7), 2 NaN clips (3, 37) that fail to encode
    assert train["skipped"].pop("test bad item") == 4
    assert sum(train["skipped"].values()) + sum(val["skipped"].values()) == 2
    assert train["num_clips"] + val["num_clips"] == 48 - 4 - 4 - 2
    assert train["num_shards"] > 2


def test_parts_merged_equal_one_build(one_worker, tmp_path):
    parts = [tmp_path / f"part{i}" for i in range(2)]
    for i, part in enumerate(parts):
        _build(part, workers=1, part=i, parts=2)
    main(["shards", "merge", *map(str, parts), "--out", str(tmp_path / "merged")])
    for split in ("train", "val"):
        whole, merged = one_worker / split, tmp_path / "merged" / split
        a, b = _clips(whole), _clips(merged)
        assert sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)
        mw, mm = Manifest.load(whole), Manifest.load(merged)
        for key in ("num_clips", "num_frames", "skipped", "representation", "fps"):
            assert mm[key] == mw[key], key
        np.testing.assert_allclose(mm.mean, mw.mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(mm.std, mw.std, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(mm.sums.total_sq, mw.sums.total_sq, rtol=1e-9)
        # shards keep their bytes: each merged shard is a part's shard, renamed
        part_shards = {e["sha256"] for p in parts for e in Manifest.load(p / split)["shards"]}
        assert {e["sha256"] for e in mm["shards"]} == part_shards
        assert [e["name"] for e in mm["shards"]] == [f"shard-{i:06d}.tar" for i in range(len(part_shards))]
        assert mm["parts"] == [str(p / split) for p in parts]
    linked = merge_shard_sets([p / "train" for p in parts], tmp_path / "linked", link=True, log=lambda m: None)
    assert linked["shards"] == Manifest.load(tmp_path / "merged" / "train")["shards"]
    assert os.path.samefile(linked.shard_paths[0], parts[0] / "train" / "shard-000000.tar")  # hard links


def test_merge_refuses_mismatched_or_taken(tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    _build(a, val_fraction=0.0, options={"num_clips": 12})
    build(SOURCE, b, "humanml3d263", "smpl22", 30.0, options={"num_clips": 12})
    with pytest.raises(UsageError, match=r"fps 30.0, but .* has 20.0"):
        merge_shard_sets([a, b], tmp_path / "out", log=lambda m: None)
    with pytest.raises(UsageError, match="already holds a shard set"):
        merge_shard_sets([a], b, log=lambda m: None)
    with pytest.raises(UsageError, match="--part must be in"):
        _build(tmp_path / "c", part=2, parts=2)
    (tmp_path / "c").mkdir()
    with pytest.raises(SystemExit) as exit:
        main(["shards", "merge", str(tmp_path / "c"), "--out", str(tmp_path / "d")])
    assert exit.value.code == 2 and "neither a shard set" in capsys.readouterr().err


def test_a_helpers_failure_stops_the_build(tmp_path):
    flag = tmp_path / "fail"
    flag.write_text("")
    with pytest.raises(RuntimeError, match="interrupted at item 23"):  # raised in whichever process read it
        _build(tmp_path / "failed", workers=2, options={"fail_flag": str(flag)})
    assert not (tmp_path / "failed").exists()  # a failed build removes the folders it created


class _Finalized:
    """Garbage (it holds itself) that adds a line with the pid of each process whose collector finalizes it."""

    def __init__(self, record: Path):
        self.record, self.itself = record, self

    def __del__(self):
        with self.record.open("a") as lines:
            lines.write(f"{os.getpid()}\n")


def test_the_build_collects_its_garbage_before_it_forks_its_workers(tmp_path):
    """A worker forked with this process's uncollected garbage would finalize it itself, where a finalizer
    that waits on one of this process's threads (a DDP wrapper ending its gloo group) waits for ever: the
    build collects first, so nothing of it is finalized in a worker (whose collector runs here before it
    reads each item)."""
    import gc

    record = tmp_path / "finalized_by"
    gc.disable()  # the garbage stays uncollected up to the build: only explicit collections run
    try:
        _Finalized(record)
        _build(tmp_path / "out", workers=2, options={"num_clips": 8, "collect": True})
    finally:
        gc.enable()
    assert record.read_text().split() == [str(os.getpid())]  # here, once, and in no worker


def test_killed_parallel_build_resumes(one_worker, tmp_path):
    out = tmp_path / "killed"
    code = f"from pathlib import Path; from helpers.lazy_walks import build; build(Path({str(out)!r}), workers=2, " \
           "options={'delay': 0.05})"
    process = subprocess.Popen([sys.executable, "-c", code], cwd=Path(__file__).parent,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = out / "train" / BUILD_STATE
    deadline = time.monotonic() + 120
    while not state.exists():
        assert process.poll() is None and time.monotonic() < deadline, "the build ended before it could be killed"
        time.sleep(0.01)
    helpers = psutil.Process(process.pid).children(recursive=True)
    process.send_signal(signal.SIGKILL)
    process.wait()
    _, alive = psutil.wait_procs(helpers, timeout=15)  # they notice their main process is gone
    assert helpers and not alive, f"helper processes outlived the killed build: {alive}"
    finished = json.loads(state.read_text())["shards"]
    assert finished and not (out / "train" / "manifest.json").exists()
    summaries = _build(out, workers=2)
    assert summaries[0].resumed_shards == len(finished)
    for split in ("train", "val"):
        assert _set(out / split) == _set(one_worker / split)


def test_progress_lines():
    stream = io.StringIO()
    progress = BuildProgress(total=10, interval=0.0, stream=stream, label="omg shards build x")
    progress.update(None)
    progress.update(ValueError("bad"))
    lines = stream.getvalue().splitlines()
    assert len(lines) == 2
    assert lines[-1].startswith("omg shards build x: 2 of 10 (20%) items read, 0 clips, 1 skipped, ")
    assert "items/s" in lines[-1] and lines[-1].endswith("left")


def test_cli_build_reports_progress_as_it_goes(tmp_path, capsys):
    main(["shards", "build", "--source", SOURCE, "--out", str(tmp_path / "p"), "--fps", "20", "--max_clips", "4",
          "--progress", "0.000001", "--option.num_clips", "12"])
    err = capsys.readouterr().err.splitlines()
    assert len(err) >= 12 and err[0].startswith(f"omg shards build {tmp_path / 'p'}: 1 of 12 (8%) items read")


def test_real_clips_build_alike_with_two_workers(shared_motion, tmp_path):
    """The real BVH / DeepMimic / ASF-AMC folder: helpers read the files; the same shards as one worker."""
    sets = []
    for workers in (1, 2):
        out = tmp_path / f"real{workers}"
        build("bvh-dir", out, "humanml3d263", "smpl22", 20.0, input=str(shared_motion), val_fraction=0.1,
              shuffle_buffer=1000, workers=workers)
        sets.append([_set(out / split) for split in ("train", "val")])
    assert sets[0] == sets[1]
    assert sets[0][0]["manifest"]["num_clips"] + sets[0][1]["manifest"]["num_clips"] == 75  # the 75 human clips


def test_array_script_builds_its_part(tmp_path):
    """launch/shards_array.sbatch: the array task's part, the part count, a worker per CPU, the part's folder."""
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "omg").write_text('#!/usr/bin/env bash\nprintf "%s\\n" "$@"\n')
    (fake / "omg").chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}", "SLURM_ARRAY_TASK_ID": "7",
           "SLURM_ARRAY_TASK_MIN": "4", "SLURM_ARRAY_TASK_COUNT": "6", "SLURM_CPUS_PER_TASK": "12"}
    script = Path(__file__).parents[1] / "launch" / "shards_array.sbatch"
    out = subprocess.run(["bash", str(script), "amass", "/data/AMASS", "shards/amass", "--fps", "30"],
                         capture_output=True, text=True, env=env, check=True).stdout.splitlines()
    assert out == ["shards", "build", "--source", "amass", "--input", "/data/AMASS", "--out",
                   "shards/amass.parts/part-003", "--part", "3", "--parts", "6", "--workers", "12", "--fps", "30"]
    env.pop("SLURM_ARRAY_TASK_ID")
    failed = subprocess.run(["bash", str(script), "amass", "/data/AMASS", "shards/amass"], capture_output=True,
                            text=True, env=env)
    assert failed.returncode != 0 and "array job" in failed.stderr
