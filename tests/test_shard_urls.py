"""Shard sets behind URLs: ``pipe:`` commands and fsspec URLs, manifests fetched the same way,
the manifest's integrity checks on streamed shards, and `omg fit` on a mixture read through a pipe."""

from __future__ import annotations

import logging
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from helpers import write_toy_shards
from omg.data.datamodule import MotionDataModule
from omg.data.shards import Manifest, ShardError, iter_tar
from omg.errors import UsageError


def _dm(train, **kw):
    defaults = dict(batch_size=4, max_len=30, min_len=10, batches_per_epoch=6, num_workers=0, shuffle_buffer=8)
    return MotionDataModule(train, **{**defaults, **kw})


def _ids(loader):
    return [b["id"] for b in loader]


def test_a_pipe_set_is_named_by_its_manifest_command(toy_shards):
    m = Manifest.load(f"pipe:cat {toy_shards}/manifest.json")
    assert m.location == f"pipe:cat {toy_shards}/manifest.json"
    assert m.shard_urls == [f"pipe:cat {toy_shards}/shard-{i:06d}.tar" for i in range(8)]
    assert m.expected(m.shard_urls[3]) == Manifest.load(toy_shards).expected(f"{toy_shards}/shard-000003.tar")
    samples = list(iter_tar(m.shard_urls[0], **m.expected(m.shard_urls[0]), whole=True))
    assert [s["__key__"] for s in samples] == [f"clip_{i:04d}" for i in range(5)]
    # a command with arguments after the file name: the file name is replaced where it stands
    m = Manifest.load(f"pipe:cat {toy_shards}/manifest.json -")
    assert m.shard_urls[1] == f"pipe:cat {toy_shards}/shard-000001.tar -"
    assert m.expected(m.shard_urls[1])["samples"] == 5


@pytest.mark.parametrize("num_workers", [0, 2])
def test_training_through_pipe_urls_reads_the_same_stream(toy_shards, num_workers):
    local = _ids(_dm(str(toy_shards), num_workers=num_workers).train_dataloader())
    piped = _dm(f"pipe:cat {toy_shards}/manifest.json", num_workers=num_workers)
    assert piped.train_urls[0].startswith("pipe:cat ") and piped.spec == _dm(str(toy_shards)).spec
    assert _ids(piped.train_dataloader()) == local
    pattern = _dm(f"pipe:cat {toy_shards}/shard-{{000000..000007}}.tar", num_workers=num_workers)
    assert all(pattern.shard_checks[url].keys() == {"sha256", "samples", "size"} for url in pattern.train_urls)
    assert _ids(pattern.train_dataloader()) == local
    assert _dm(str(toy_shards / "manifest.json")).train_urls == _dm(str(toy_shards)).train_urls  # a local manifest


def test_streamed_shards_are_verified_against_the_manifest(tmp_path, caplog):
    shards = write_toy_shards(tmp_path / "s", num_clips=30, max_clips=5)
    first = shards / "shard-000000.tar"
    data = bytearray(first.read_bytes())
    data[-2000] ^= 0xFF  # garbled inside a payload: the tar still parses
    first.write_bytes(bytes(data))
    url = f"pipe:cat {shards}/manifest.json"
    m = Manifest.load(url)
    with pytest.raises(ShardError) as e:
        list(iter_tar(m.shard_urls[0], **m.expected(m.shard_urls[0])))
    assert e.value.check == "sha256" and e.value.shard == f"pipe:cat {first}"
    cut = shards / "shard-000001.tar"
    cut.write_bytes(cut.read_bytes()[:512 * (cut.stat().st_size // 1024)])  # half the shard
    with pytest.raises(ShardError) as e:
        list(iter_tar(m.shard_urls[1], **m.expected(m.shard_urls[1])))
    assert e.value.shard == f"pipe:cat {cut}"
    with caplog.at_level(logging.WARNING):
        batches = list(_dm(url, batches_per_epoch=20, max_bad_fraction=0.5).train_dataloader())
    seen = {int(i.split(".")[1]) for b in batches for i in b["id"]}
    assert len(batches) == 20 and seen and not seen & set(range(10))  # nothing of the two bad shards
    assert f"pipe:cat {first}" in caplog.text and "sha256" in caplog.text


def test_a_directory_url_reads_through_fsspec(toy_shards):
    fsspec = pytest.importorskip("fsspec")
    memory = fsspec.filesystem("memory")
    for path in toy_shards.iterdir():
        memory.pipe(f"/sets/toy/{path.name}", path.read_bytes())
    try:
        dm = _dm("memory://sets/toy")
        assert dm.train_urls[0] == "memory://sets/toy/shard-000000.tar"
        assert _ids(dm.train_dataloader()) == _ids(_dm(str(toy_shards)).train_dataloader())
        assert Manifest.load("memory://sets/toy/manifest.json").shard_urls == dm.train_urls
    finally:
        memory.rm("/sets", recursive=True)


@pytest.mark.parametrize("url, error", [
    ("pipe:cat /nonexistent/manifest.json", "pipe:cat /nonexistent/manifest.json: the manifest cannot be fetched "
                                            r"\(the command exited with 1: cat: /nonexistent/manifest.json: No such"),
    ("pipe:cat /nonexistent/set", "a pipe: set must print its manifest.json"),
    ("nosuchscheme://bucket/set", "nosuchscheme://bucket/set/manifest.json: the manifest cannot be fetched "
                                  r"\(no reader for nosuchscheme:// URLs"),
])
def test_unreadable_set_urls_are_one_line_errors(url, error):
    with pytest.raises(UsageError, match=error) as e:
        _dm(url)
    assert "\n" not in str(e.value)


def test_a_manifest_fetched_by_url_is_checked_like_a_local_one(toy_shards, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(toy_shards, broken)
    (broken / "manifest.json").write_text('{"schema_version": 1}')
    with pytest.raises(UsageError, match=f"pipe:cat {broken}/manifest.json: invalid manifest: missing keys"):
        _dm(f"pipe:cat {broken}/manifest.json")


def test_inspect_checks_a_set_behind_a_pipe(toy_shards, capsys):
    from omg.tools.shards import shards_inspect

    # a buffer of the set's size: the default 1000 would read the 40 clips 25 times over, a process each shard
    shards_inspect([f"pipe:cat {toy_shards}/manifest.json"], shuffle_buffer=40)
    out = capsys.readouterr().out
    assert out.startswith(f"pipe:cat {toy_shards}/manifest.json: 40 clips")
    assert "a batch of 16 through a shuffle buffer of 40 holds on average: captions" in out
    assert "8 of 8 shards verified against the manifest; 40 valid samples, 0 problems" in out


def test_fit_on_a_mixture_read_through_a_pipe_stores_the_pooled_stats(h263_shards, tmp_path):
    """`omg fit` end to end: one set behind `pipe:cat`, one local; the checkpoint's spec (what
    `omg generate` normalises with) holds the mixture's pooled statistics."""
    from helpers.configs import write_config
    from omg.cli import main
    from omg.lit.checkpoint import load_module

    train = [{"path": f"pipe:cat {h263_shards / 'train'}/manifest.json", "weight": 0.8},
             {"path": str(h263_shards / "val"), "weight": 0.2}]
    config = write_config(tmp_path / "mix.yaml", "unused", tmp_path / "run", max_steps=4, num_workers=1)
    text = (tmp_path / "mix.yaml").read_text().replace("train: unused", "train: " + repr(train).replace("'", '"'))
    (tmp_path / "mix.yaml").write_text(text)
    main(["fit", "--config", config])
    module = load_module(tmp_path / "run" / "ckpt" / "last.ckpt")
    pooled = _dm(train).spec
    single = _dm(str(h263_shards / "train")).spec
    assert module.spec == pooled and not np.allclose(pooled.mean, single.mean)


INJECTED = ["shard-$(touch PWNED).tar", "shard-`touch PWNED`.tar", "shard-000000.tar;touch PWNED",
            "shard-000000.tar|touch PWNED", "shard-000000.tar touch PWNED", "shard-000000.tar&&touch PWNED"]


@pytest.mark.parametrize("name", INJECTED)
def test_a_shard_name_that_would_run_a_command_is_refused(toy_shards, tmp_path, monkeypatch, capsys, name):
    """A pipe: set puts each shard name of its manifest into its command, which a shell runs: a name
    that is not shard-NNNNNN.tar is one error line naming the manifest and the name, and nothing runs."""
    import json

    from omg.cli import main

    monkeypatch.chdir(tmp_path)  # where the injected command would create its marker
    data = json.loads((toy_shards / "manifest.json").read_text())
    data["shards"][0]["name"] = name
    (toy_shards / "manifest.json").write_text(json.dumps(data))
    url = f"pipe:cat {toy_shards}/manifest.json"
    with pytest.raises(SystemExit) as exit:
        main(["shards", "inspect", url])
    err = capsys.readouterr().err.strip()
    assert exit.value.code == 2 and "\n" not in err, err
    assert err.startswith(f"omg: error: {url}: invalid manifest: shards[0] needs a 'name' of the form "
                          "shard-NNNNNN.tar") and repr(name) in err
    with pytest.raises(UsageError, match="needs a 'name' of the form shard-NNNNNN.tar"):
        _dm(url)
    assert not (tmp_path / "PWNED").exists()


def test_pipe_shard_names_are_shell_quoted_and_a_hanging_manifest_command_stops(toy_shards):
    import shlex
    import time

    from omg.data.shards import read_url

    m = Manifest.load(f"pipe:cat {toy_shards}/manifest.json")
    m.data["shards"][0]["name"] = "shard 0.tar"  # not a name the manifest check lets through: quoted all the same
    assert m.shard_urls[0] == f"pipe:cat {toy_shards}/{shlex.quote('shard 0.tar')}"
    start = time.monotonic()
    with pytest.raises(OSError, match="the command did not end within 1 s and was stopped"):
        read_url("pipe:echo '{}'; sleep 30", timeout=1)
    assert time.monotonic() - start < 10


def test_ctrl_c_that_interrupts_no_wait_still_ends_a_pipe_command_read(tmp_path):
    """A Ctrl-C whose handler runs just before the wait for a `pipe:` command begins interrupts nothing: `omg
    fit` would ignore it for as long as a manifest command stalls. Sent to another thread here, which does the
    same: its handler runs there, and the main thread's wait goes on. The read returns to Python every
    SIGNAL_CHECK_S, so the Ctrl-C still ends it, and the command is killed."""
    import threading
    import time

    from omg.data.shards import read_url

    ctrl_c = signal.signal(signal.SIGINT, signal.default_int_handler)  # Python's own, as a terminal starts omg
    marker = tmp_path / "started"

    def ctrl_c_elsewhere():
        deadline = time.monotonic() + 30
        while not marker.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # its C handler runs on this thread

    helper = threading.Thread(target=ctrl_c_elsewhere)
    helper.start()
    start = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            read_url(f"pipe:touch {marker}; sleep 40; echo '{{}}'", timeout=60)
    finally:
        helper.join()
        signal.signal(signal.SIGINT, ctrl_c)
    assert time.monotonic() - start < 20, "the Ctrl-C was acted on only when the command ended"
    assert not _command_lines_naming(str(marker)), "the command outlived the read"


def _command_lines_naming(text: str) -> list[str]:
    found = []
    for entry in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            line = entry.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:  # ended meanwhile
            continue
        if text in line:
            found.append(line)
    return found
