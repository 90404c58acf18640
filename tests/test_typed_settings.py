"""The typed groups of a module's optimizer settings and loss weights (``optim``, ``loss``): shown and checked
key by key by ``--help`` and ``--print_config``, one range check each, and the older flat keys of configs,
command lines and checkpoints read into them."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import yaml

from helpers import MINI, REPO
from helpers.habit import CATEGORIES
from omg.cli import main
from omg.errors import UsageError
from omg.lit.base import OptimSettings
from omg.lit.habit import HabitLossWeights, StepOptimSettings
from omg.lit.omgpt import OmniMotionLossWeights, OmniMotionOptimSettings
from omg.lit.pretrain import DiffusionLossWeights

# config: each of its module's value groups and the keys it accepts
GROUPS = {
    "pretrain": {"optim": OptimSettings, "loss": DiffusionLossWeights},
    "controlnet": {"optim": OptimSettings, "loss": DiffusionLossWeights},
    "evaluator": {"optim": OptimSettings},
    "habit_vqvae": {"optim": StepOptimSettings, "loss": HabitLossWeights},
    "habit_prior": {"optim": OptimSettings},
    "omgpt": {"optim": OmniMotionOptimSettings, "loss": OmniMotionLossWeights},
}
CASES = [(config, group) for config, groups in GROUPS.items() for group in groups]


def _run(capsys, *args: str) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(list(args))
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _accepted(cls: type) -> str:
    return ", ".join(f.name for f in dataclasses.fields(cls))


@pytest.mark.parametrize(("config", "group"), CASES)
def test_an_unknown_nested_key_is_one_line_naming_it_and_the_accepted_keys(capsys, tmp_path, config, group):
    cls = GROUPS[config][group]
    path = str(REPO / f"configs/mini/{config}.yaml")
    code, _, err = _run(capsys, "fit", "--config", path, f"--model.init_args.{group}.bogus=1", "--print_config")
    assert code == 2 and err.count("\n") == 1
    assert err == f"omg: error: model.init_args.{group}.bogus: unknown key 'bogus'; accepted keys: {_accepted(cls)}\n"
    # the same key in a config file
    extra = tmp_path / "extra.yaml"
    extra.write_text(yaml.safe_dump({"model": {"init_args": {group: {"bogus": 1}}}}))
    code, _, err = _run(capsys, "fit", "--config", path, "--config", str(extra), "--print_config")
    assert code == 2 and err.count("\n") == 1 and "bogus" in err and _accepted(cls) in err, err


@pytest.mark.parametrize("config", list(GROUPS))
def test_print_config_and_help_show_every_key_of_each_group(capsys, config):
    path = str(REPO / f"configs/mini/{config}.yaml")
    code, out, _ = _run(capsys, "fit", "--config", path, "--print_config")
    assert code == 0
    init_args = yaml.safe_load(out)["model"]["init_args"]
    for group, cls in GROUPS[config].items():
        assert list(init_args[group]) == [f.name for f in dataclasses.fields(cls)]
    model = yaml.safe_load((REPO / f"configs/mini/{config}.yaml").read_text())["model"]["class_path"]
    code, out, _ = _run(capsys, "fit", "--model.help", model.rpartition(".")[2])
    assert code == 0
    for group, cls in GROUPS[config].items():
        for f in dataclasses.fields(cls):
            assert f"--model.{group}.{f.name} " in out, (group, f.name)


def test_each_group_checks_its_ranges_once_in_one_line():
    for cls, field, value, message in [
            (OptimSettings, "lr", 0.0, "model.optim.lr must be a finite number > 0, got 0.0"),
            (OptimSettings, "weight_decay", -1.0, "model.optim.weight_decay must be a finite number >= 0, got -1.0"),
            (OptimSettings, "betas", (0.9, 1.0), "model.optim.betas must be two numbers in [0, 1), got (0.9, 1.0)"),
            (OptimSettings, "warmup_steps", -1, "model.optim.warmup_steps must be an integer >= 0, got -1"),
            (StepOptimSettings, "lr_after", 0.0, "model.optim.lr_after must be > 0, got 0.0"),
            (StepOptimSettings, "lr_switch", 1.5, "model.optim.lr_switch must be in [0, 1], got 1.5"),
            (StepOptimSettings, "lr", -1.0, "model.optim.lr must be a finite number > 0, got -1.0"),
            (OmniMotionOptimSettings, "schedule", "linear", "model.optim.schedule must be constant or cosine, got "
                                                            "'linear'"),
            (DiffusionLossWeights, "foot_weight", float("inf"), "model.loss.foot_weight must be a finite number >= 0"),
            (HabitLossWeights, "flow_weight", -0.1, "model.loss.flow_weight must be a finite number >= 0, got -0.1"),
            (OmniMotionLossWeights, "ee_weight", -1.0, "model.loss.ee_weight must be a finite number >= 0")]:
        with pytest.raises(UsageError) as e:
            cls(**{field: value})
        assert str(e.value).startswith(message) and "\n" not in str(e.value)


def test_older_flat_keys_are_read_into_their_groups_with_one_warning_each(capsys, tmp_path):
    """A user's older YAML (``lr:`` under model.init_args) and command line (``--model.init_args.vel_weight``,
    ``--model.lr``) keep working: each key is read as its group's field, with one warning naming the new key."""
    old = yaml.safe_load((REPO / "configs/mini/pretrain.yaml").read_text())
    init_args = old["model"]["init_args"]
    init_args.update(init_args.pop("optim"))  # the older shape: lr and warmup_steps flat
    assert {"lr", "warmup_steps"} <= set(init_args)
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(old))
    with pytest.warns(UserWarning) as record:
        code, out, _ = _run(capsys, "fit", "--config", str(path), "--model.init_args.vel_weight", "7",
                            "--model.weight_decay=0.25", "--print_config")
    assert code == 0
    printed = yaml.safe_load(out)["model"]["init_args"]
    assert printed["optim"] == {"lr": 1e-3, "weight_decay": 0.25, "betas": [0.9, 0.999], "warmup_steps": 20}
    assert printed["loss"] == {"vel_weight": 7.0, "foot_weight": 30.0}
    assert "lr" not in printed and "vel_weight" not in printed
    warned = {str(w.message) for w in record}
    for key, group in [("lr", "optim"), ("warmup_steps", "optim"), ("vel_weight", "loss"), ("weight_decay", "optim")]:
        assert f"model.init_args.{key} is read as model.init_args.{group}.{key}, where it is set now" in warned
    # both spellings of one field: one line
    both = tmp_path / "both.yaml"
    both.write_text(yaml.safe_dump({"model": {"init_args": {"lr": 1.0, "optim": {"lr": 2.0}}}}))
    code, _, err = _run(capsys, "fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--config", str(both),
                        "--print_config")
    assert code == 2 and err == ("omg: error: model.init_args.lr and model.init_args.optim.lr are both set: keep "
                                 "model.init_args.optim.lr only (model.init_args.lr is its older name)\n")


def _flat(hparams: dict) -> dict:
    """Hyper-parameters as omg wrote them before the groups: optim's and loss's fields at the top level."""
    flat = {k: v for k, v in hparams.items() if k not in ("optim", "loss")}
    for group in ("optim", "loss"):
        flat.update(hparams.get(group) or {})
    return flat


def test_a_checkpoint_with_flat_hyper_parameters_loads_into_the_groups(tmp_path):
    """Checkpoints written before the groups hold their fields flat (``lr``, ``alpha``, and a habit prior's ``vq``
    too): each loads with the settings it was trained with, and a fresh save keeps the groups."""
    from omg.data.datamodule import MotionDataModule
    from omg.lit.checkpoint import class_path, load_module
    from omg.lit.habit import HabitPriorModule, HabitVQModule

    quatvel = MotionDataModule(str(MINI / "animal_quatvel/train"), batch_size=2, num_workers=0).spec
    vq = HabitVQModule(CATEGORIES, flavor="tiny", text_encoder="hash", spec=quatvel,
                       loss={"alpha": 0.4, "flow_weight": 0.2}, optim={"lr": 3e-3, "lr_switch": 0.7})
    assert vq.hparams["optim"] == {"lr": 3e-3, "weight_decay": 0.0, "betas": [0.9, 0.99], "warmup_steps": 0,
                                   "lr_after": 1e-5, "lr_switch": 0.7}

    def save(module, hparams, name):
        path = tmp_path / name
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams,
                    "module_class": class_path(type(module))}, path)
        return str(path)

    old_vq = save(vq, _flat(dict(vq.hparams)), "vq.ckpt")
    assert "lr" in torch.load(old_vq, weights_only=True)["hyper_parameters"]
    loaded = load_module(old_vq)
    assert loaded.optim == vq.optim and loaded.loss == vq.loss
    assert loaded.hparams["optim"] == vq.hparams["optim"] and "lr" not in loaded.hparams

    prior = HabitPriorModule(save(vq, dict(vq.hparams), "vq_new.ckpt"), optim={"warmup_steps": 3})
    hparams = {**_flat(dict(prior.hparams)), "vq": _flat(prior.hparams["vq"])}
    loaded = load_module(save(prior, hparams, "prior.ckpt"))
    assert loaded.optim == prior.optim and loaded.vq.optim == vq.optim and loaded.vq.loss == vq.loss
