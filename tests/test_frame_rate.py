"""One frame rate across stages: the prior's rate is the fine-tuning data's and the output's."""

from __future__ import annotations

import lightning as L
import pytest

from helpers import TINY_DIT, walking_clip
from omg.data.datamodule import MotionDataModule
from omg.data.shards import ShardWriter
from omg.errors import UsageError
from omg.motion import get_representation
from omg.skeleton import SMPL22


def shards_at(root, fps: float):
    rep = get_representation("humanml3d263", SMPL22)
    ShardWriter(root, rep, fps, max_clips=8, log=lambda m: None).write(walking_clip(i, fps=fps) for i in range(8))
    return root


@pytest.fixture(scope="session")
def prior_30fps(tmp_path_factory):
    """A stage-1 checkpoint trained (one step) on 30-fps shards."""
    from omg.lit.pretrain import PretrainModule

    root = tmp_path_factory.mktemp("prior30")
    data = MotionDataModule(str(shards_at(root / "shards", 30.0)), batch_size=4, max_len=30, min_len=10,
                            batches_per_epoch=1, num_workers=0, shuffle_buffer=4)
    model = PretrainModule(flavor="mini", dit=TINY_DIT, spec=data.spec, optim={"warmup_steps": 1})
    trainer = L.Trainer(accelerator="cpu", max_steps=1, logger=False, enable_progress_bar=False,
                        enable_model_summary=False, enable_checkpointing=False, limit_val_batches=0)
    trainer.fit(model, data)
    trainer.save_checkpoint(root / "prior.ckpt")
    return root / "prior.ckpt"


def test_fine_tuning_data_at_another_rate_is_refused(prior_30fps, tmp_path):
    from omg.lit.controlnet import ControlNetModule

    data_20 = MotionDataModule(str(shards_at(tmp_path / "s20", 20.0)))
    with pytest.raises(UsageError,
                       match=r"the pretrained model and the fine-tuning shards differ: fps 30.0 vs 20.0 .*--fps 30"):
        ControlNetModule(pretrained=str(prior_30fps), text_encoder="hash", spec=data_20.spec)
    data_30 = MotionDataModule(str(shards_at(tmp_path / "s30", 30.0)))
    module = ControlNetModule(pretrained=str(prior_30fps), text_encoder="hash", spec=data_30.spec)
    assert module.spec.fps == module.data_spec.fps == 30.0


def test_generated_bvh_is_at_the_training_rate(prior_30fps, tmp_path):
    from omg.cli import main

    out = tmp_path / "gen"
    main(["generate", "--unconditional", "--ckpt", str(prior_30fps), "--num_samples", "1", "--length", "1",
          "--steps", "2", "--no_preview", "--out", str(out)])
    bvh = (out / "sample_000.bvh").read_text()
    frame_time = float(bvh.split("Frame Time:")[1].split()[0])
    frames = int(bvh.split("Frames:")[1].split()[0])
    assert frame_time == pytest.approx(1 / 30, abs=1e-6) and frames == 30


def test_omg_fit_refuses_a_prior_of_another_rate_in_one_line_naming_the_fix(prior_30fps, tmp_path, capsys):
    """The rate statement of docs/guide/pretraining_data.md: the paper's pretraining data is at 30 fps, a prior
    generates at its rate, and `omg fit` of the ControlNet on 20-fps data (HumanML3D's) stops in one line naming
    what to set: pretraining shards built with --fps 20 and data.max_len 200 (OMG's L = 300 frames at 30 fps, the
    same 10 s)."""
    from helpers import REPO
    from omg.cli import main

    shards = shards_at(tmp_path / "s20", 20.0)
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "--config", str(REPO / "configs/mini/controlnet.yaml"),
              f"--model.init_args.pretrained={prior_30fps}", "--model.init_args.text_encoder=hash",
              f"--data.train={shards}", "--data.val=null", "--data.num_workers=0", "--data.min_len=10",
              f"--trainer.default_root_dir={tmp_path / 'run'}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("omg: error: "), err
    assert "fps 30.0 vs 20.0" in err and "--fps 20" in err and "data.max_len 200" in err, err
