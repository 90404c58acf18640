"""The real clips end to end, as a new user runs them: one command to shards, the mini pretraining
config trained on them, a generated motion exported to BVH and read back."""

from __future__ import annotations

import json

import numpy as np

from helpers import REPO, TINY_DIT_ARG
from omg.cli import main
from omg.io.bvh import read_bvh
from omg.skeleton import SMPL22


def test_real_clips_to_shards_to_training_to_bvh(shared_motion, tmp_path):
    shards = tmp_path / "real"
    main(["shards", "build", "--source", "bvh-dir", "--input", str(shared_motion), "--out", str(shards),
          "--skeleton", "smpl22", "--representation", "humanml3d263", "--fps", "20", "--val_fraction", "0.1"])
    counts = [json.loads((shards / s / "manifest.json").read_text())["num_clips"] for s in ("train", "val")]
    assert sum(counts) == 75 and min(counts) > 0

    root = tmp_path / "run"
    main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), f"--data.train={shards}/train",
          f"--data.val={shards}/val", "--data.batch_size=4", "--data.max_len=40", "--data.num_workers=0",
          "--trainer.max_steps=3", "--trainer.val_check_interval=3", f"--trainer.default_root_dir={root}",
          f"--trainer.callbacks.dirpath={root}/checkpoints", "--trainer.enable_progress_bar=false",
          TINY_DIT_ARG])
    ckpt = root / "checkpoints/last.ckpt"
    assert ckpt.exists() and (root / "version_0/config.yaml").exists()

    out = tmp_path / "gen"
    main(["generate", "--unconditional", "--ckpt", str(ckpt), "--num_samples", "1", "--length", "2", "--steps", "4",
          "--no_preview", "--out", str(out)])
    joints = np.load(out / "sample_000.joints.npy")
    bvh = read_bvh(out / "sample_000.bvh")
    assert bvh.num_joints == 22 and len(bvh) == len(joints) == 40 and bvh.fps == 20.0
    positions = bvh.positions()[:, [bvh.names.index(n) for n in SMPL22.names]]
    assert np.abs(positions - joints).max() < 0.01  # IK of an untrained model's motion: close, not exact
