"""Faults of a running `omg fit`: SIGTERM, a stalled data worker, too many bad samples in a
worker. Each ends with one line on stderr and an exit code a scheduler can act on."""

from __future__ import annotations

import os
import signal
import time

import pytest
import torch
import yaml
from lightning.pytorch.callbacks import Callback

from omg.cli import SIGTERM_EXIT, main


class SigtermAt(Callback):
    """Sends this process SIGTERM during a step, as a scheduler or `scancel` would."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


def write_config(path, shards, root, *, max_steps=8, num_workers=0, callbacks=(), **data):
    config = {
        "seed_everything": 0,
        "trainer": {
            "accelerator": "cpu", "devices": 1, "max_steps": max_steps, "enable_progress_bar": False,
            "enable_model_summary": False, "limit_val_batches": 0, "num_sanity_val_steps": 0,
            "default_root_dir": str(root),
            "callbacks": [{"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                           "init_args": {"dirpath": str(root / "ckpt"), "save_last": True, "every_n_train_steps": 2}},
                          *callbacks],
        },
        "model": {"class_path": "PretrainModule",
                  "init_args": {"flavor": "mini", "dit": {"n_layers": 1, "d_model": 32, "n_heads": 2}, "lr": 1e-3,
                                "warmup_steps": 2, "ema_decay": 0.9}},
        "data": {"train": str(shards), "batch_size": 4, "max_len": 30, "min_len": 10, "batches_per_epoch": 5,
                 "num_workers": num_workers, "shuffle_buffer": 8, **data},
    }
    path.write_text(yaml.safe_dump(config))
    return str(path)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("omg:")]
    assert len(lines) == 1, err[-2000:]
    return lines[0]


def test_sigterm_saves_a_checkpoint_exits_nonzero_and_resumes_exactly(h263_shards, tmp_path, capsys, caplog):
    shards = h263_shards / "train"
    full = write_config(tmp_path / "full.yaml", shards, tmp_path / "full")
    main(["fit", "--config", full])
    sigterm = {"class_path": "test_run_faults.SigtermAt", "init_args": {"step": 4}}
    stopped = write_config(tmp_path / "stopped.yaml", shards, tmp_path / "stopped", callbacks=[sigterm])
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", stopped])
    assert e.value.code == SIGTERM_EXIT  # not 0: the run did not finish
    line = one_error_line(capsys)
    assert line.startswith("omg: interrupted by SIGTERM at step 5;") and "interrupted.ckpt" in line
    assert (tmp_path / "stopped" / "ckpt" / "interrupted.ckpt").is_file()
    # `--ckpt_path last` takes the newest of last.ckpt (step 4) and interrupted.ckpt (step 5)
    resumed = write_config(tmp_path / "resumed.yaml", shards, tmp_path / "stopped")
    with caplog.at_level("INFO"):
        main(["fit", "--config", resumed, "--ckpt_path", "last"])
    assert ("Restoring states from the checkpoint path at " + str(tmp_path / "stopped" / "ckpt" / "interrupted.ckpt")
            in caplog.text)
    a = torch.load(tmp_path / "full" / "ckpt" / "last.ckpt", weights_only=False)
    b = torch.load(tmp_path / "stopped" / "ckpt" / "last.ckpt", weights_only=False)
    assert a["global_step"] == b["global_step"] == 8
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    assert torch.equal(a["noise_rng"], b["noise_rng"])
    # a run without --ckpt_path starts afresh, even beside another run's checkpoints
    caplog.clear()
    with caplog.at_level("INFO"):
        main(["fit", "--config", resumed])
    assert "Restoring states" not in caplog.text


def _stall(self, rng):
    time.sleep(60)
    yield from ()


def test_a_stalled_data_worker_stops_the_run_with_one_line(h263_shards, tmp_path, capsys, monkeypatch):
    from omg.data.datamodule import MotionStream

    monkeypatch.setattr(MotionStream, "_samples", _stall)  # the forked worker inherits it
    config = write_config(tmp_path / "c.yaml", h263_shards / "train", tmp_path / "run", num_workers=1, timeout=2)
    start = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", config])
    assert e.value.code == 2 and time.perf_counter() - start < 50
    line = one_error_line(capsys)
    assert "data.timeout=2" in line and "stalled" in line


def test_too_many_bad_samples_in_a_worker_is_one_line(h263_shards, tmp_path, capsys):
    import shutil
    import tarfile

    from omg.data.shards import Manifest
    from test_shards import _rewrite_member

    shards = tmp_path / "s"
    shutil.copytree(h263_shards / "train", shards)
    for path in Manifest.load(shards).shard_paths:  # half the samples of every shard
        with tarfile.open(path) as tar:
            keys = sorted({name.split(".")[0] for name in tar.getnames()})
        for key in keys[::2]:
            _rewrite_member(path, f"{key}.motion.npy", b"garbage")
    config = write_config(tmp_path / "c.yaml", shards, tmp_path / "run", num_workers=1, verify_shards=False)
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", config])
    assert e.value.code == 2
    line = one_error_line(capsys)
    assert "samples were bad" in line and "max_bad_fraction" in line and "DataLoader worker" not in line


def test_a_non_finite_loss_names_the_batch_clips_in_one_line(h263_shards, tmp_path, capsys):
    """Values that overflow the loss (1e30: finite, so every sample decodes) in a set read without
    checksums: one line with the step and the batch's clips, not a FloatingPointError traceback."""
    import io
    import re
    import shutil
    import tarfile

    import numpy as np

    from omg.data.shards import Manifest
    from test_shards import _rewrite_member

    shards = tmp_path / "s"
    shutil.copytree(h263_shards / "train", shards)
    huge = io.BytesIO()
    np.save(huge, np.full((40, 263), 1e30, np.float32))
    for path in Manifest.load(shards).shard_paths:
        with tarfile.open(path) as tar:
            keys = sorted({name.split(".")[0] for name in tar.getnames()})
        for key in keys:
            _rewrite_member(path, f"{key}.motion.npy", huge.getvalue())
    config = write_config(tmp_path / "c.yaml", shards, tmp_path / "run", max_steps=2, verify_shards=False)
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", config])
    assert e.value.code == 2
    line = one_error_line(capsys)
    assert "non-finite loss" in line and "at step 0" in line
    assert re.search(r"on the batch of clips walk\d+, walk\d+, walk\d+, walk\d+;", line), line  # batch_size 4
