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
    ``--model.lr``, ``--model.init_args.stance_root``) keep working: each key is read as its group's field, with
    one warning naming the new key."""
    old = yaml.safe_load((REPO / "configs/mini/pretrain.yaml").read_text())
    init_args = old["model"]["init_args"]
    init_args.update(init_args.pop("optim"))  # the older shape: lr and warmup_steps flat
    assert {"lr", "warmup_steps"} <= set(init_args)
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(old))
    with pytest.warns(UserWarning) as record:
        code, out, _ = _run(capsys, "fit", "--config", str(path), "--model.init_args.vel_weight", "7",
                            "--model.weight_decay=0.25", "--model.init_args.stance_root=0.5", "--print_config")
    assert code == 0
    printed = yaml.safe_load(out)["model"]["init_args"]
    assert printed["optim"] == {"lr": 1e-3, "weight_decay": 0.25, "betas": [0.9, 0.999], "warmup_steps": 20}
    assert printed["loss"] == {"vel_weight": 7.0, "foot_weight": 30.0}
    assert printed["sampling"] == {"stance_root": 0.5, "smoothing": 0.0}
    assert "lr" not in printed and "vel_weight" not in printed and "stance_root" not in printed
    warned = {str(w.message) for w in record}
    for key, group in [("lr", "optim"), ("warmup_steps", "optim"), ("vel_weight", "loss"), ("weight_decay", "optim"),
                       ("stance_root", "sampling")]:
        assert f"model.init_args.{key} is read as model.init_args.{group}.{key}, where it is set now" in warned
    # both spellings of one field: one line
    both = tmp_path / "both.yaml"
    both.write_text(yaml.safe_dump({"model": {"init_args": {"lr": 1.0, "optim": {"lr": 2.0}}}}))
    code, _, err = _run(capsys, "fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--config", str(both),
                        "--print_config")
    assert code == 2 and err == ("omg: error: model.init_args.lr and model.init_args.optim.lr are both set: keep "
                                 "model.init_args.optim.lr only (model.init_args.lr is its older name)\n")


VALUE_GROUPS = ("optim", "loss", "order", "codebook", "source", "species", "sampling")


def _flat(hparams: dict) -> dict:
    """Hyper-parameters as omg wrote them before the groups: the value groups' fields at the top level."""
    flat = {k: v for k, v in hparams.items() if k not in VALUE_GROUPS}
    for group in VALUE_GROUPS:
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
                       loss={"alpha": 0.4, "flow_weight": 0.2}, optim={"lr": 3e-3, "lr_switch": 0.7},
                       order={"habit_order": "kl_then_flows", "habit_fraction": 0.3},
                       codebook={"quantizer": "nearest", "temperature": 0.5, "code_reset": False, "ema_decay": 0.9})
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
    assert loaded.hparams["codebook"] == vq.hparams["codebook"] and loaded.hparams["order"] == vq.hparams["order"]
    assert loaded.hparams["species"] == vq.hparams["species"] and torch.equal(loaded.category_text, vq.category_text)
    q = loaded.vqvae.quantizer
    assert (q.mode, q.temperature, q.code_reset, q.decay) == ("nearest", 0.5, False, 0.9)
    assert (loaded.habit_order, loaded.habit_fraction, loaded.flows) == ("kl_then_flows", 0.3, None)

    prior = HabitPriorModule(save(vq, dict(vq.hparams), "vq_new.ckpt"), optim={"warmup_steps": 3})
    hparams = {**_flat(dict(prior.hparams)), "vq": _flat(prior.hparams["vq"])}
    loaded = load_module(save(prior, hparams, "prior.ckpt"))
    assert loaded.optim == prior.optim and loaded.vq.optim == vq.optim and loaded.vq.loss == vq.loss
    assert loaded.vq.hparams["codebook"] == vq.hparams["codebook"] and loaded.vq.habit_order == "kl_then_flows"


def test_a_diffusion_checkpoint_with_a_flat_stance_root_loads_it_into_its_sampling_defaults(tmp_path):
    """A diffusion checkpoint written before ``sampling`` was a group holds ``stance_root`` flat: it loads as its
    sampling default, smoothing off, and samples as the grouped checkpoint does."""
    from helpers import TINY_DIT
    from helpers.checkpoints import SPEC
    from omg.lit.checkpoint import class_path, load_module
    from omg.lit.pretrain import PretrainModule
    from omg.lit.sampling import SamplingSettings

    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=SPEC, ema_decay=0, sampling={"stance_root": 0.5})
    assert module.hparams["sampling"] == {"stance_root": 0.5, "smoothing": 0.0}
    paths = {}
    for name, hparams in (("grouped", dict(module.hparams)), ("flat", _flat(dict(module.hparams)))):
        paths[name] = tmp_path / f"{name}.ckpt"
        torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams,
                    "module_class": class_path(type(module))}, paths[name])
    assert torch.load(paths["flat"], weights_only=True)["hyper_parameters"]["stance_root"] == 0.5
    flat, grouped = (load_module(paths[name]).eval() for name in ("flat", "grouped"))
    assert (flat.stance_root, flat.smoothing, flat.hparams["sampling"]) == (0.5, 0.0, module.hparams["sampling"])
    settings = SamplingSettings(steps=2, seed=3)
    assert torch.equal(flat.sample(None, [12], settings), grouped.sample(None, [12], settings))


ABBREVIATED = "unknown option (options are never abbreviated); did you mean"


@pytest.mark.parametrize(("args", "message"), [
    # LightningCLI's own parser
    (["fit", "--config", "{pretrain}", "--trainer.max_st", "3", "--print_config"],
     f"--trainer.max_st: {ABBREVIATED} --trainer.max_steps?"),
    # the parser jsonargparse builds for the model's class, with or without init_args
    (["fit", "--config", "{pretrain}", "--model.init_args.ema", "0.5", "--print_config"],
     f"--model.init_args.ema: {ABBREVIATED} --model.init_args.ema_decay?"),
    (["fit", "--config", "{pretrain}", "--model.ema", "0.5", "--print_config"],
     f"--model.init_args.ema: {ABBREVIATED} --model.init_args.ema_decay?"),
    # a nested group's key: the typo of the issue, which set loss.vel_weight without a word
    (["fit", "--config", "{pretrain}", "--model.init_args.loss.vel", "3", "--print_config"],
     "model.init_args.loss.vel: unknown key 'vel'; did you mean model.init_args.loss.vel_weight? (accepted keys: "
     "vel_weight, foot_weight)"),
    (["fit", "--config", "{omgpt}", "--data.human.trai", "x", "--print_config"],
     "data.human.trai: unknown key 'trai'; did you mean data.human.train?"),
    # a tool's parser, and a tool's subcommand's
    (["generate", "--num_samp", "3", "a dog jumps", "--print_config"], f"--num_samp: {ABBREVIATED} --num_samples?"),
    (["shards", "inspect", "--batch", "3", "shards/mini/animal_maa/val", "--print_config"],
     f"--batch: {ABBREVIATED} --batch_size?"),
])
def test_an_abbreviated_option_is_refused_in_one_line_naming_the_key_meant(capsys, args, message):
    """argparse takes an unambiguous prefix of a long option for it, so ``--model.init_args.loss.vel 3`` set
    ``loss.vel_weight`` and ``--trainer.max_st`` ``max_steps`` silently. Every omg parser refuses it: LightningCLI's,
    those jsonargparse builds below it (the model's class, a typed group), a tool's and a subcommand's; the line
    names the option given and the closest real key."""
    configs = {"pretrain": str(REPO / "configs/mini/pretrain.yaml"), "omgpt": str(REPO / "configs/mini/omgpt.yaml")}
    code, out, err = _run(capsys, *[arg.format(**configs) for arg in args])
    assert code == 2 and err.count("\n") == 1 and not out, err
    assert err.startswith(f"omg: error: {message}"), err


def test_full_keys_and_their_dashed_spellings_still_work(capsys):
    """The keys spelled in full, and the dashed spellings of the earlier CLI (docs/guide/reliability.md:
    ``--num-samples``, ``--trainer.max-steps``, ``--model.init-args.ema-decay``), are taken as before."""
    code, out, _ = _run(capsys, "fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--trainer.max-steps", "3",
                        "--model.init-args.ema-decay", "0.5", "--model.init_args.loss.vel_weight", "7",
                        "--data.human.train", "x", "--print_config")
    assert code == 0
    printed = yaml.safe_load(out)
    assert printed["trainer"]["max_steps"] == 3 and printed["model"]["init_args"]["ema_decay"] == 0.5
    assert printed["model"]["init_args"]["loss"]["vel_weight"] == 7.0 and printed["data"]["human"]["train"] == "x"
    code, out, _ = _run(capsys, "generate", "--num-samples", "2", "a dog jumps", "--print_config")
    assert code == 0 and yaml.safe_load(out)["num_samples"] == 2


@pytest.mark.parametrize("spelling", [["--model.init_args.source.retrieval_bank=null"],
                                      ["--model.init_args.source.retrieval_bank", "null"],
                                      ["--model.init_args.source.retrieval_bank=~"]])
def test_a_null_group_field_on_the_command_line_is_none_and_keeps_the_groups_other_fields(capsys, spelling):
    """A command line's null for one field of a group that a config sets is None (jsonargparse alone reads it as
    the string 'None' inside a subclass's init_args), the group's other fields as the config says."""
    configs = ["--config", str(REPO / "configs/mini/omgpt_eval.yaml"),
               "--config", str(REPO / "configs/mini/omgpt_eval_retrieval.yaml")]
    code, out, _ = _run(capsys, "test", *configs, *spelling, "--print_config")
    assert code == 0
    source = yaml.safe_load(out)["model"]["init_args"]["source"]
    assert source["retrieval_bank"] is None
    assert (source["human_source"], source["retrieval_top_k"], source["retrieval_draw"]) == ("retrieval", 32,
                                                                                             "similarity")


def test_constructors_take_about_a_dozen_parameters():
    """Each LightningModule of omg.lit takes its settings in groups: about a dozen constructor parameters, at most 14
    (the ControlNet's: OMG's 13 and omg's spatial hints, one group; OmniMotionGPT had 17, the habit VQ-VAE 18)."""
    import inspect

    import omg.lit

    counts = {name: len(inspect.signature(getattr(omg.lit, name)).parameters) for name in omg.lit.__all__}
    assert max(counts.values()) <= 14, counts


def test_older_flat_keys_of_the_new_groups_are_read_for_their_model_class_only(capsys, tmp_path):
    """OmniMotionGPT's human-source settings and the habit VQ-VAE's order and codebook settings, flat on the command
    line or in a config, are read into ``source``, ``order`` and ``codebook`` with one warning each; the habit
    codebook's ``ema_decay`` is read so for the habit VQ-VAE only (every other module's ``ema_decay`` is its
    weight EMA's, its own parameter)."""
    with pytest.warns(UserWarning) as record:
        code, out, _ = _run(capsys, "fit", "--config", str(REPO / "configs/mini/omgpt.yaml"),
                            "--model.init_args.retrieval_top_k", "5", "--model.human_source=retrieval",
                            "--print_config")
    assert code == 0
    source = yaml.safe_load(out)["model"]["init_args"]["source"]
    assert (source["retrieval_top_k"], source["human_source"]) == (5, "retrieval")
    warned = {str(w.message) for w in record}
    assert "model.init_args.retrieval_top_k is read as model.init_args.source.retrieval_top_k, where it is set now" \
        in warned

    old = yaml.safe_load((REPO / "configs/mini/habit_vqvae.yaml").read_text())
    init_args = old["model"]["init_args"]
    init_args.update(init_args.pop("order"))
    init_args.update(init_args.pop("codebook"), ema_decay=0.9)
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(old))
    with pytest.warns(UserWarning) as record:
        code, out, _ = _run(capsys, "fit", "--config", str(path), "--model.init_args.quantizer", "nearest",
                            "--print_config")
    assert code == 0
    printed = yaml.safe_load(out)["model"]["init_args"]
    assert printed["codebook"] == {"quantizer": "nearest", "temperature": 0.1, "code_reset": True, "ema_decay": 0.9}
    assert printed["order"] == {"habit_order": "flow_prior", "habit_fraction": 0.2}
    warned = {str(w.message) for w in record}
    for key, group in [("habit_order", "order"), ("quantizer", "codebook"), ("ema_decay", "codebook")]:
        assert f"model.init_args.{key} is read as model.init_args.{group}.{key}, where it is set now" in warned

    code, out, _ = _run(capsys, "fit", "--config", str(REPO / "configs/mini/pretrain.yaml"),
                        "--model.init_args.ema_decay", "0.5", "--print_config")
    assert code == 0 and yaml.safe_load(out)["model"]["init_args"]["ema_decay"] == 0.5


def test_a_python_caller_passing_an_older_flat_keyword_gets_one_line_naming_its_group():
    from omg.lit.habit import HabitVQModule
    from omg.lit.omgpt import OmniMotionModule

    for cls, key, value, group in [(OmniMotionModule, "retrieval_top_k", 3, "source"),
                                   (HabitVQModule, "code_reset", False, "codebook"),
                                   (HabitVQModule, "habit_order", "kl_then_flows", "order"),
                                   (HabitVQModule, "lr", 1e-3, "optim")]:
        with pytest.raises(TypeError) as e:
            cls(**{key: value})
        assert str(e.value) == (f"{cls.__name__}() takes {key} in its {group} group now: pass "
                                f"{group}={{{key!r}: {value!r}}} (model.init_args.{group}.{key})")


def test_the_architecture_fields_of_a_group_come_from_the_checkpoint_and_locations_never():
    """Under --ckpt_path a value group's architecture field (``codebook.code_reset``: the paper's row the codebook
    was trained as) is the checkpoint's, a run that says otherwise refused in one line; its other fields (how codes
    are drawn) are the run's. A group's location fields (``source.human_source``, ``source.retrieval_bank``) are
    never read from a checkpoint, grouped or flat as older checkpoints hold them."""
    from omg.lit.checkpoint import inert_hparams, run_hparams
    from omg.lit.habit import HabitVQModule
    from omg.lit.omgpt import OmniMotionModule

    saved = {"codebook": {"quantizer": "soft", "temperature": 0.1, "code_reset": True, "ema_decay": 0.99}}
    taken = run_hparams(HabitVQModule, saved, {"codebook": {"quantizer": "nearest", "code_reset": True}}, "vq.ckpt")
    assert taken == {"codebook": {"temperature": 0.1, "ema_decay": 0.99}}
    with pytest.raises(UsageError) as e:
        run_hparams(HabitVQModule, saved, {"codebook": {"code_reset": False}}, "vq.ckpt")
    assert str(e.value).startswith("--model.init_args.codebook.code_reset: the checkpoint vq.ckpt was trained with "
                                   "true; this run's config says false")

    grouped = {"source": {"human_source": "pipe:touch x", "retrieval_top_k": 3, "retrieval_bank": "s3://bank"}}
    assert inert_hparams(OmniMotionModule, grouped) == {"source": {"retrieval_top_k": 3}}
    flat = {"human_source": "pipe:touch x", "retrieval_bank": "s3://bank", "retrieval_top_k": 3}
    assert inert_hparams(OmniMotionModule, flat) == {"retrieval_top_k": 3}
