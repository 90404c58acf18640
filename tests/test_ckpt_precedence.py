"""What the user writes wins over what a checkpoint remembers (``omg test|validate --ckpt_path``).

A setting that does not shape the weights (sampling, retrieval, evaluation, loss weights, the optimizer) comes
from the command line, else the config files, else the checkpoint; one that does (``architecture_hparams``:
widths, the text encoder, the codebook, ...) comes from the checkpoint, and a config or flag that says
otherwise is refused in one line naming the key, both values and the checkpoint. For each family, through
the command a user runs, on tiny untrained checkpoints; the settings are read off the module the test loop
ran (``Seen``), as the loop used them.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import lightning as L
import pytest
import torch
import yaml

from helpers import MINI, REPO, TINY_DIT
from helpers.configs import write_config
from helpers.habit import CATEGORIES
from omg.cli import main

pytestmark = pytest.mark.xdist_group("ckpt_precedence")  # the tests share the `ckpts` fixture's checkpoints


class Seen(L.Callback):
    """Keeps the module that ``omg test`` or ``omg validate`` ran (a config names it by class path)."""

    module: L.LightningModule | None = None

    def on_test_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        Seen.module = pl_module

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        Seen.module = pl_module


DATA = {  # each family's validation clips, a batch or two of them
    "h263": {"val": str(MINI / "human263/val"), "batch_size": 4, "max_len": 30, "min_len": 20},
    "maa": {"val": str(MINI / "animal_maa/val"), "batch_size": 4, "max_len": 32, "min_len": 20, "clips": "whole"},
    "quatvel": {"val": str(MINI / "animal_quatvel/val"), "batch_size": 8, "max_len": 64, "min_len": 64,
                "clips": "windows"},
}


@pytest.fixture(scope="session")
def ckpts(tmp_path_factory) -> dict[str, str]:
    """One checkpoint per family, each holding values of the settings under test that are neither the class
    defaults nor what the runs below set: PretrainModule's from two steps of ``omg fit`` (its hyper-parameters
    as LightningCLI records them), the others' saved from a freshly built module as Lightning saves one."""
    from helpers.omgpt import tiny_module
    from omg.data.datamodule import MotionDataModule
    from omg.lit.checkpoint import class_path
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.evaluator import EvaluatorModule
    from omg.lit.habit import HabitPriorModule, HabitVQModule

    root = tmp_path_factory.mktemp("precedence")
    torch.manual_seed(0)
    config = write_config(root / "pre.yaml", MINI / "human263/train", root / "pre", max_steps=2)
    main(["fit", "--config", config, "--model.init_args.sampling.stance_root=0.25",
          "--model.init_args.loss.vel_weight=7", "--model.init_args.loss.foot_weight=5"])
    paths = {"pretrain": str(root / "pre/ckpt/last.ckpt")}

    def save(module, name):
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                    "module_class": class_path(type(module)), "pytorch-lightning_version": L.__version__},
                   root / name)
        paths[name] = str(root / name)
        return paths[name]

    save(ControlNetModule(pretrained=paths["pretrain"], text_encoder="hash", moc={"d_c": 16, "num_experts": 2},
                          guidance_scale=2.0, eot_drop=0.3, sampling={"stance_root": 0.1}, ema_decay=0), "controlnet")
    maa = MotionDataModule(str(MINI / "animal_maa/train"), batch_size=2, num_workers=0).spec
    save(EvaluatorModule(text_encoder="hash", flavor="mini", evaluator={"n_layers": 1, "d_model": 32, "embed_dim": 32},
                         r_precision_pool=4, spec=maa, optim={"warmup_steps": 7}), "evaluator")
    save(tiny_module(maa, source={"retrieval_top_k": 3, "retrieval_draw": "uniform", "retrieval_temperature": 0.5},
                     loss={"cons_weight": 0.3}),
         "omgpt")
    quatvel = MotionDataModule(str(MINI / "animal_quatvel/train"), batch_size=2, num_workers=0).spec
    vq = save(HabitVQModule(CATEGORIES, flavor="tiny", text_encoder="hash",
                            spec=quatvel, loss={"alpha": 0.4, "beta": 0.03, "kl_weight": 2e-3}), "habit_vq")
    save(HabitPriorModule(vq, posterior_sample=True, optim={"lr": 3e-4, "warmup_steps": 3}), "habit_prior")
    return paths


def _config(path: Path, model: str, data: str, init_args: dict) -> str:
    """An ``omg test`` config: the model's class and ``init_args``, the family's data, ``Seen``, one batch."""
    config = {
        "trainer": {"accelerator": "cpu", "devices": 1, "default_root_dir": str(path.parent / "run"),
                    "limit_test_batches": 1, "limit_val_batches": 1, "enable_progress_bar": False,
                    "enable_model_summary": False, "callbacks": [{"class_path": f"{__name__}.Seen"}]},
        "model": {"class_path": model, "init_args": init_args},
        "data": {**DATA[data], "num_workers": 0},
    }
    path.write_text(yaml.safe_dump(config))
    return str(path)


def _flags(values: dict) -> list[str]:
    return [f"--model.init_args.{k}={json.dumps(v) if isinstance(v, (dict, list)) else v}" for k, v in values.items()]


# family: (command, class, data, what the config files set, what the command line sets, what the loop ran with:
# the command line's over the config's, the config's over the checkpoint's, the checkpoint's where neither says)
CASES = {
    "pretrain": ("test", "PretrainModule", "h263",
                 {"flavor": "mini", "dit": {"n_layers": 2}, "sampling": {"stance_root": 0.5},
                  "loss": {"vel_weight": 10.0}},
                 {"loss.vel_weight": 20.0},
                 lambda m: {"stance_root": m.stance_root, "vel_weight": m.loss.vel_weight,
                            "foot_weight": m.loss.foot_weight},
                 {"stance_root": 0.5, "vel_weight": 20.0, "foot_weight": 5.0}),
    "controlnet": ("test", "ControlNetModule", "h263",
                   {"guidance_scale": 3.0, "sampling": {"stance_root": 0.2}, "text_encoder": "hash"},
                   {"sampling.stance_root": 0.4},
                   lambda m: {"guidance_scale": m.guidance_scale, "stance_root": m.stance_root, "eot_drop": m.eot_drop},
                   {"guidance_scale": 3.0, "stance_root": 0.4, "eot_drop": 0.3}),
    "evaluator": ("validate", "EvaluatorModule", "maa",
                  {"r_precision_pool": 5, "optim": {"weight_decay": 0.5}},
                  {"r_precision_pool": 6},
                  lambda m: {"pool": m.val_r_precision.pool_size, "weight_decay": m.optim.weight_decay,
                             "warmup_steps": m.optim.warmup_steps},
                  {"pool": 6, "weight_decay": 0.5, "warmup_steps": 7}),
    # configs/omgpt_eval.yaml's retrieval: the similarity draw among the 32 nearest clips at T = 0.1
    "omgpt": ("test", "OmniMotionModule", "maa",
              {"source": {"retrieval_top_k": 32, "retrieval_draw": "similarity", "retrieval_temperature": 0.1}},
              {"source.retrieval_temperature": 0.2},
              lambda m: {"top_k": m.retrieval_top_k, "draw": m.retrieval_draw, "temperature": m.retrieval_temperature,
                         "cons_weight": m.weights["cons"]},
              {"top_k": 32, "draw": "similarity", "temperature": 0.2, "cons_weight": 0.3}),
    "habit_vq": ("test", "HabitVQModule", "quatvel",
                 {"categories": CATEGORIES, "loss": {"alpha": 0.6}, "codebook": {"quantizer": "nearest"}},
                 {"loss.beta": 0.05},
                 lambda m: {"alpha": m.loss.alpha, "beta": m.loss.beta, "kl_weight": m.loss.kl_weight,
                            "quantizer": m.vqvae.quantizer.mode},
                 {"alpha": 0.6, "beta": 0.05, "kl_weight": 2e-3, "quantizer": "nearest"}),
    "habit_prior": ("test", "HabitPriorModule", "quatvel",
                    {"posterior_sample": False},
                    {"optim.warmup_steps": 5},
                    lambda m: {"posterior_sample": m.posterior_sample, "warmup_steps": m.optim.warmup_steps,
                               "lr": m.optim.lr},
                    {"posterior_sample": False, "warmup_steps": 5, "lr": 3e-4}),
}


@pytest.mark.parametrize("family", list(CASES))
def test_the_command_line_beats_the_config_and_the_config_beats_the_checkpoint(ckpts, family, tmp_path):
    command, model, data, config, flags, observe, expected = CASES[family]
    Seen.module = None
    main([command, "--config", _config(tmp_path / "run.yaml", model, data, config), "--ckpt_path", ckpts[family],
          *_flags(flags)])
    assert Seen.module is not None and type(Seen.module).__name__ == model
    assert observe(Seen.module) == expected


OMGPT_FIT = str(REPO / "configs/mini/omgpt.yaml")

# family: (what the run says against the checkpoint: a config file's path or flags, the one line it gets)
REFUSALS = {
    "pretrain": ([], {"flavor": "base"}, 'flavor: the checkpoint {ckpt} was trained with "mini"; this run\'s config '
                                         'says "base"'),
    "pretrain-dit": ([], {"dit": {"n_layers": 3}}, "dit.n_layers: the checkpoint {ckpt} was trained with 2; this "
                                                   "run's config says 3"),
    "controlnet": ([], {"moc": {"d_c": 32}}, "moc.d_c: the checkpoint {ckpt} was trained with 16; this run's config "
                                             "says 32"),
    "evaluator": ([], {"text_encoder": "minilm"}, 'text_encoder: the checkpoint {ckpt} was trained with "hash"; this '
                                                  'run\'s config says "minilm"'),
    "omgpt": ([], {"text_encoder": "minilm"}, 'text_encoder: the checkpoint {ckpt} was trained with "hash"; this '
                                              'run\'s config says "minilm"'),
    # the mini fit config (MiniLM, other switches) under a checkpoint trained otherwise: its first contradiction
    "omgpt-fit-config": (["--config", OMGPT_FIT], {}, None),
    # the tiny preset's codebook, no overrides: a field the checkpoint does not name
    "habit_vq": ([], {"habit": {"num_codes": 8}}, "habit.num_codes: the checkpoint {ckpt} was trained with its "
                                                  "default (the field unset); this run's config says 8"),
    "habit_prior": ([], {"vq": {"flavor": "mini"}}, 'vq.flavor: the checkpoint {ckpt} was trained with "tiny"; this '
                                                    'run\'s config says "mini"'),
}


@pytest.mark.parametrize("case", list(REFUSALS))
def test_a_run_that_contradicts_the_checkpoints_architecture_is_refused_in_one_line(ckpts, case, tmp_path, capsys):
    family = case.split("-")[0]
    command, model, data, config, _, _, _ = CASES[family]  # the run's settings, which it may set
    configs, flags, message = REFUSALS[case]
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main([command, *configs, "--config", _config(tmp_path / "run.yaml", model, data, config),
              "--ckpt_path", ckpts[family], *_flags(flags)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.strip().splitlines()) == 1, err
    if message is None:  # the first contradiction, whichever key it is
        assert re.match(rf"omg: error: --model\.init_args\.[\w.]+: the checkpoint {re.escape(ckpts[family])} was "
                        r"trained with .+; this run's config says .+", err), err
    else:
        assert err.startswith("omg: error: --model.init_args." + message.format(ckpt=ckpts[family])), err
    assert not (tmp_path / "run").exists()  # refused before the run folder is made


def test_run_hparams_merges_in_order_and_leaves_unset_architecture_to_the_checkpoint():
    """The rule itself: a mapping that names some of the checkpoint's fields with its values agrees; a ``null``
    given for an architecture key (a run's saved config.yaml lists ``base: null``) leaves it to the checkpoint."""
    from omg.errors import UsageError
    from omg.lit.checkpoint import run_hparams
    from omg.lit.controlnet import ControlNetModule

    saved = {"base": {"flavor": "mini", "dit": {"n_layers": 2}}, "moc": {"d_c": 16, "num_experts": 2},
             "guidance_scale": 2.0, "eot_drop": 0.3}
    given = {"base": None, "moc": {"d_c": 16}, "guidance_scale": 4.5, "optim": {"lr": 1e-3}}
    assert run_hparams(ControlNetModule, saved, given, "c.ckpt") == {
        "base": saved["base"], "moc": saved["moc"], "eot_drop": 0.3}
    with pytest.raises(UsageError, match=r"^--model.init_args.base.dit.n_heads: the checkpoint c.ckpt was trained "
                                         r"with its default \(the field unset\); this run's config says 4 "):
        run_hparams(ControlNetModule, saved, {"base": {"dit": {"n_layers": 2, "n_heads": 4}}}, "c.ckpt")
    assert run_hparams(None, saved, given, "c.ckpt") == {"eot_drop": 0.3}  # a class that names none: all the run's


def test_a_run_under_its_own_saved_config_loads_its_checkpoint(ckpts, tmp_path):
    """``omg test --config RUN/version_0/config.yaml --ckpt_path``: the config the fit saved (every argument, the
    defaults too) agrees with its checkpoint; its settings are the run's."""
    saved = Path(ckpts["pretrain"]).parents[1] / "version_0" / "config.yaml"
    Seen.module = None
    main(["test", "--config", str(saved), "--ckpt_path", ckpts["pretrain"], "--data.val", DATA["h263"]["val"],
          f"--trainer.default_root_dir={tmp_path}", "--trainer.limit_test_batches=1",
          f'--trainer.callbacks+={{"class_path": "{__name__}.Seen"}}'])
    assert Seen.module.hparams["dit"] == TINY_DIT and Seen.module.stance_root == 0.25
