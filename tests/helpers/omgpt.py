"""OmniMotionGPT in tests: the tiny config, the mini data's streams, a tiny module, and a few steps of
``omg fit --config configs/mini/omgpt.yaml`` (the ``omgpt_ckpt`` fixture)."""

from __future__ import annotations

import json
from pathlib import Path

from helpers import MINI, REPO

TINY = {"joint_layers": 1, "joint_heads": 2, "temporal_dim": 32, "temporal_layers": 1, "latent_dim": 32,
        "latent_layers": 1, "dropout": 0.0}


def data(path, **kw):
    """A data module of a mini set (whole clips of 20-32 frames, batches of 4, in-process)."""
    from omg.data.datamodule import MotionDataModule

    args = dict(batch_size=4, max_len=32, min_len=20, num_workers=0, shuffle_buffer=32, clips="whole")
    return MotionDataModule(str(path), **{**args, **kw})


HUMAN = dict(train=str(MINI / "human_maa/train"), batch_size=4, max_len=32, min_len=20, num_workers=0,
             shuffle_buffer=32, clips="whole")  # the mini human stream of whole clips


def paired(path, human: dict | None = None, **kw):
    """The paired data module of a mini animal set (as ``data``) and the mini human set (``human``: its arguments
    over ``HUMAN``'s)."""
    from omg.data.paired import PairedDataModule

    args = dict(batch_size=4, max_len=32, min_len=20, num_workers=0, shuffle_buffer=32, clips="whole")
    return PairedDataModule(str(path), human={**HUMAN, **(human or {})}, **{**args, **kw})


def human_batch(**kw) -> dict:
    """The first training batch of the mini human stream (``HUMAN``'s arguments, ``kw`` over them)."""
    from omg.data.datamodule import MotionDataModule

    return next(iter(MotionDataModule(**{**HUMAN, **kw}).train_dataloader()))


def tiny_module(spec, **kw):
    """The tiny OmniMotionModule of these tests (hash text, no EMA), its human spec the mini human set's (what a
    fit on ``paired`` data sets when it starts)."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.omgpt import OmniMotionModule

    module = OmniMotionModule(flavor="mini", config=TINY, text_encoder="hash", spec=spec, ema_decay=0, **kw)
    module.use_human_spec(MotionDataModule(**HUMAN).spec)
    return module


def fit_config() -> dict:
    """The networks of ``fit_mini``: configs/mini/omgpt.yaml's ``config`` (omg's variant switches) at TINY's sizes."""
    import yaml

    mini = yaml.safe_load((REPO / "configs/mini/omgpt.yaml").read_text())["model"]["init_args"].get("config") or {}
    return {**mini, **TINY}


def fit_mini(root: Path) -> Path:
    """`omg fit --config configs/mini/omgpt.yaml`, 4 steps of the tiny model with hash text; its last checkpoint."""
    from omg.cli import main

    main(["fit", "--config", str(REPO / "configs/mini/omgpt.yaml"), "--trainer.max_steps=4",
          f"--trainer.default_root_dir={root}", "--trainer.enable_progress_bar=false", "--trainer.val_check_interval=4",
          "--trainer.enable_model_summary=false", "--model.init_args.text_encoder=hash",
          f"--model.init_args.config={json.dumps(fit_config())}", "--data.batch_size=4",
          "--data.human.batch_size=4"])
    return root / "checkpoints/last.ckpt"
