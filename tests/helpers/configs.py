"""Configs in tests: the shipped YAMLs parsed against the real classes as ``omg fit`` composes them,
and a tiny ``omg fit`` config written for fault and pipe tests."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import yaml
from jsonargparse import ActionConfigFile
from lightning.pytorch.cli import LightningArgumentParser

import omg.callbacks  # noqa: F401  (short class names in configs resolve among imported modules)
import omg.lit  # noqa: F401
from helpers import REPO, TINY_DIT
from omg.data.paired import PairedDataModule
from omg.tools.lightning import model_clip_sampling

# an overlay -> the config it completes
OVERLAYS = {"mini/omgpt_self_eval.yaml": REPO / "configs/mini/omgpt_eval.yaml",
            "mini/omgpt_eval_retrieval.yaml": REPO / "configs/mini/omgpt_eval.yaml",
            "omgpt_eval_retrieval.yaml": REPO / "configs/omgpt.yaml",
            "omgpt_variant.yaml": REPO / "configs/omgpt.yaml", "omgpt_eval.yaml": REPO / "configs/omgpt.yaml",
            "habit_eval.yaml": REPO / "configs/habit_vqvae.yaml",
            "habit_animalml3d.yaml": REPO / "configs/habit_vqvae.yaml",
            "mini/habit_eval.yaml": REPO / "configs/mini/habit_vqvae.yaml"}


def parse(path: Path):
    """A shipped config under configs/ parsed against the real Trainer, module and data classes."""
    parser = LightningArgumentParser(exit_on_error=False)
    parser.add_argument("--config", action=ActionConfigFile)
    parser.add_argument("--seed_everything", type=int | bool, default=True)
    parser.add_lightning_class_args(L.Trainer, "trainer")
    parser.add_lightning_class_args(L.LightningModule, "model", subclass_mode=True)
    parser.add_lightning_class_args(PairedDataModule, "data")
    parser.link_arguments("model", "data.clip_sampling", compute_fn=model_clip_sampling, apply_on="parse")  # as omg fit
    # a data-only config (configs/data/) or an overlay follows the config it completes, as
    # `omg fit --config A --config B` composes them
    overlay = OVERLAYS.get(path.relative_to(REPO / "configs").as_posix())
    base = REPO / "configs/pretrain_base.yaml" if path.parent.name == "data" else overlay
    return parser.parse_args([*(["--config", str(base)] if base else []), "--config", str(path)])


def write_config(path, shards, root, *, max_steps=8, num_workers=0, callbacks=(), top_k=1, **data):
    """An ``omg fit`` YAML at ``path``: the tiny DiT on ``shards``, one CPU device, no validation, a
    checkpoint every 2 steps into ``root/ckpt`` (last.ckpt kept); ``data``: more data fields. Its path."""
    config = {
        "seed_everything": 0,
        "trainer": {
            "accelerator": "cpu", "devices": 1, "max_steps": max_steps, "enable_progress_bar": False,
            "enable_model_summary": False, "limit_val_batches": 0, "num_sanity_val_steps": 0,
            "default_root_dir": str(root),
            "callbacks": [{"class_path": "lightning.pytorch.callbacks.ModelCheckpoint",
                           "init_args": {"dirpath": str(root / "ckpt"), "save_last": True, "every_n_train_steps": 2,
                                         "save_top_k": top_k}},
                          *callbacks],
        },
        "model": {"class_path": "PretrainModule",
                  "init_args": {"flavor": "mini", "dit": TINY_DIT, "optim": {"lr": 1e-3, "warmup_steps": 2},
                                "ema_decay": 0.9}},
        "data": {"train": str(shards), "batch_size": 4, "max_len": 30, "min_len": 10, "batches_per_epoch": 5,
                 "num_workers": num_workers, "shuffle_buffer": 8, **data},
    }
    path.write_text(yaml.safe_dump(config))
    return str(path)
