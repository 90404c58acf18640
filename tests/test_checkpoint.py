"""Checkpoints to fp32/EMA safetensors: Lightning files, DeepSpeed ZeRO-2 directories, bad inputs."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
import torch
from safetensors.torch import load_file

from helpers import TINY_DIT
from helpers.checkpoints import SPEC, write_zero2_checkpoint, zero_tensor_bytes
from omg.cli import main as omg
from omg.errors import UsageError
from omg.lit.checkpoint import class_path, convert, load_checkpoint, load_module
from omg.lit.ema import EMA
from omg.lit.evaluator import EvaluatorModule
from omg.lit.pretrain import PretrainModule


def model_output(module: PretrainModule) -> torch.Tensor:
    x, t = torch.randn(2, 12, 263, generator=torch.Generator().manual_seed(1)), torch.tensor([3, 700])
    with torch.no_grad():
        return module.model.eval()(x, t)


def assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype == torch.float32 and torch.equal(a[k], b[k]), k


@pytest.fixture(scope="session")
def trained(tmp_path_factory) -> tuple[PretrainModule, Path]:
    """A mini PretrainModule after one real Lightning step, and the .ckpt Lightning wrote for it.

    Its weights are perturbed first: the zero-initialised output layer would make every model
    predict 0 and hide wrong weights; and its EMA lags them, so EMA and trained weights differ.
    """
    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec=SPEC, optim={"warmup_steps": 1})
    module.ema = EMA(module.model, decay=0.9)
    with torch.no_grad():
        for p in module.model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    batch = {"motion": 0.1 * torch.randn(16, 263), "mask": torch.ones(16, dtype=torch.bool)}
    root = tmp_path_factory.mktemp("lightning")
    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=root)
    trainer.fit(module, torch.utils.data.DataLoader([batch] * 2, batch_size=2))
    trainer.save_checkpoint(root / "last.ckpt")
    ema = module.ema.state_dict()["shadow"]
    assert not torch.equal(ema["final_layer.linear.weight"], module.model.final_layer.linear.weight)
    return module, root / "last.ckpt"


def ema_state(module: PretrainModule) -> dict[str, torch.Tensor]:
    """The module's state_dict with the EMA in place of the trained ``model.`` weights."""
    return {**module.state_dict(), **{f"model.{n}": t for n, t in module.ema.state_dict()["shadow"].items()}}


def test_lightning_ckpt_loads_and_converts(trained, tmp_path):
    module, ckpt = trained
    loaded = load_module(ckpt, use_ema=False)
    assert_same(loaded.state_dict(), module.state_dict())
    assert torch.equal(model_output(loaded), model_output(module))
    assert_same(loaded.ema.state_dict()["shadow"], module.ema.state_dict()["shadow"])
    assert_same(load_module(ckpt).state_dict(), ema_state(module))  # use_ema: the EMA for inference

    summary = convert(ckpt, tmp_path / "model.safetensors")
    assert summary["parameters"] == sum(p.numel() for p in module.parameters()) and not summary["ema_weights"]
    assert summary["module_class"] == class_path(PretrainModule)  # a plain Trainer.fit does not record it
    assert_same(load_checkpoint(tmp_path / "model.safetensors")["state_dict"], module.state_dict())
    assert torch.equal(model_output(load_module(tmp_path / "model.safetensors")), model_output(module))

    assert convert(ckpt, tmp_path / "ema.safetensors", ema=True)["ema_weights"]
    converted = load_checkpoint(tmp_path / "ema.safetensors")
    assert converted["ema_weights"] and converted["hyper_parameters"]["spec"] == SPEC
    assert_same(converted["state_dict"], ema_state(module))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ema.safetensors", "model.safetensors"]  # no temp files

    # fine-tuning needs neither omg nor DeepSpeed: a plain strict load_state_dict
    fresh = PretrainModule(**converted["hyper_parameters"])
    fresh.load_state_dict(load_file(tmp_path / "ema.safetensors"))
    assert_same(fresh.state_dict(), ema_state(module))


def test_the_class_lightning_cli_records_is_used(trained, tmp_path):
    module, ckpt = trained
    checkpoint = torch.load(ckpt, weights_only=False)  # as `omg fit` (LightningCLI) writes it:
    checkpoint["hyper_parameters"].update(_class_path="omg.lit.PretrainModule",
                                          _instantiator="lightning.pytorch.cli.instantiate_module")
    torch.save(checkpoint, tmp_path / "cli.ckpt")
    assert isinstance(load_module(tmp_path / "cli.ckpt", default_class=None, expect=PretrainModule), PretrainModule)
    assert convert(tmp_path / "cli.ckpt", tmp_path / "cli.safetensors", default_class=None)["module_class"] == \
        "omg.lit.PretrainModule"
    assert torch.equal(model_output(load_module(tmp_path / "cli.safetensors", default_class=None)),
                       model_output(module))


@pytest.mark.parametrize("prefix, split_groups, open_tag_dir", [("", False, False), ("_forward_module.", True, True)])
def test_deepspeed_dir_gives_the_fp32_master_weights(trained, tmp_path, capsys, prefix, split_groups, open_tag_dir):
    module, ckpt = trained
    lightning = torch.load(ckpt, map_location="cpu", weights_only=False)
    client_state = {k: v for k, v in lightning.items() if k not in ("state_dict", "optimizer_states")}
    write_zero2_checkpoint(module, client_state, tmp_path / "last.ckpt", prefix, split_groups)
    src = tmp_path / "last.ckpt" / ("checkpoint" if open_tag_dir else "")

    omg(["convert-ckpt", str(src), str(tmp_path / "out.safetensors")])
    line = capsys.readouterr().out.strip().splitlines()[-1]  # after DeepSpeed's import warnings on CPU machines
    assert line.startswith("wrote ") and "M parameters, trained fp32 weights" in line and "MiB" in line
    out = load_checkpoint(tmp_path / "out.safetensors")["state_dict"]
    assert_same(out, module.state_dict())  # the fp32 masters, not the bf16 copies
    assert not torch.equal(out["model.input_proj.weight"], module.model.input_proj.weight.bfloat16().float())
    assert torch.equal(model_output(load_module(tmp_path / "out.safetensors")), model_output(module))

    omg(["convert-ckpt", str(src), str(tmp_path / "ema.safetensors"), "--ema"])
    assert "EMA fp32 weights" in capsys.readouterr().out
    assert_same(load_checkpoint(tmp_path / "ema.safetensors")["state_dict"], ema_state(module))
    restored = load_module(src, use_ema=False)  # the directory itself, EMA restored from the client state
    assert_same(restored.ema.state_dict()["shadow"], module.ema.state_dict()["shadow"])


class OtherModule(L.LightningModule):
    pass


def test_bad_inputs_fail_with_one_line(trained, tmp_path, capsys):
    module, ckpt = trained
    (tmp_path / "random.bin").write_bytes(torch.randn(100).numpy().tobytes())
    (tmp_path / "random.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00not json")
    (tmp_path / "empty").mkdir()
    torch.save({"weights": torch.ones(3)}, tmp_path / "weights.pt")
    convert(ckpt, tmp_path / "plain.safetensors")
    lightning = torch.load(ckpt, weights_only=False)
    no_ema = {k: v for k, v in lightning.items() if k not in ("state_dict", "optimizer_states", "ema")}
    write_zero2_checkpoint(module, no_ema, tmp_path / "no_ema")
    zero_tensor_bytes(ckpt, tmp_path / "zeroed.ckpt")
    (tmp_path / "truncated.ckpt").write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
    torch.save({**no_ema, "state_dict": {}}, tmp_path / "no_weights.ckpt")
    torch.save({**no_ema, "state_dict": {k: v for k, v in lightning["state_dict"].items() if "blocks.1." not in k}},
               tmp_path / "some_weights.ckpt")
    (tmp_path / "a_file").write_text("not a folder")
    n, dropped = len(module.state_dict()), sum("blocks.1." in k for k in module.state_dict())
    cases = {
        (str(tmp_path / "missing.ckpt"), "x.safetensors"): "missing.ckpt: no such file or directory",
        (str(tmp_path / "random.bin"), "x.safetensors"): "random.bin is not a checkpoint",
        (str(tmp_path / "random.safetensors"), "x.safetensors"): "random.safetensors is not a readable safetensors",
        (str(tmp_path / "empty"), "x.safetensors"): "empty is a directory without a `latest` file",
        (str(tmp_path / "weights.pt"), "x.safetensors"): "weights.pt is a torch file but not a Lightning checkpoint",
        (str(ckpt), str(tmp_path / "x.pt")): "must end in .safetensors",
        (str(tmp_path / "plain.safetensors"), str(tmp_path / "x.safetensors"), "--ema"): "has no EMA weights",
        (str(tmp_path / "no_ema"), str(tmp_path / "x.safetensors"), "--ema"): "has no EMA weights",
        (str(ckpt),): "the following arguments are required: dst",
        (str(tmp_path / "zeroed.ckpt"), str(tmp_path / "x.safetensors")): "zeroed.ckpt is corrupt",
        (str(tmp_path / "truncated.ckpt"), str(tmp_path / "x.safetensors")): "truncated.ckpt is corrupt",
        (str(tmp_path / "no_weights.ckpt"), str(tmp_path / "x.safetensors")): f"lacks {n} of the {n} weights of a",
        (str(tmp_path / "some_weights.ckpt"), str(tmp_path / "x.safetensors")): f"lacks {dropped} of the {n} weights",
        (str(ckpt), str(tmp_path / "a_file" / "x.safetensors")): "cannot write the converted checkpoint there",
    }
    for args, message in cases.items():
        with pytest.raises(SystemExit) as exit:
            omg(["convert-ckpt", *args])
        err = capsys.readouterr().err.strip()
        assert exit.value.code == 2 and message in err and "\n" not in err, (args, err)
    assert not (tmp_path / "x.safetensors").exists()

    with pytest.raises(UsageError, match=r"holds a omg\.lit\.pretrain\.PretrainModule checkpoint, not a .*OtherModule"):
        load_module(ckpt, expect=OtherModule)


# -- convert-ckpt --ema for every LightningModule ------------------------------------------------
# The EMA tracks module.trainable_module(): `model` for PretrainModule, `controlnet` for
# ControlNetModule. Its names are relative to that submodule; the converted file must put the EMA
# exactly in place of those weights and leave every other weight as trained.

def _fit_steps(module: L.LightningModule, batches: list[dict], root: Path, steps: int = 2) -> Path:
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=root)
    trainer.fit(module, torch.utils.data.DataLoader(batches, batch_size=2))
    trainer.save_checkpoint(root / "module.ckpt")
    return root / "module.ckpt"


def _motion_batch(i: int, text: str) -> dict:
    g = torch.Generator().manual_seed(i)
    return {"motion": 0.1 * torch.randn(16, 263, generator=g), "mask": torch.ones(16, dtype=torch.bool), "text": text}


def assert_converted_ema(ckpt: Path, dst: Path, prefix: str) -> dict[str, torch.Tensor]:
    """convert --ema wrote the checkpoint's EMA shadow under ``prefix`` and every other weight as trained."""
    saved = torch.load(ckpt, weights_only=True)
    trained_state, shadow = load_checkpoint(ckpt)["state_dict"], saved["ema"]["shadow"]
    assert any(not torch.equal(t, trained_state[prefix + n]) for n, t in shadow.items())  # a real test
    omg(["convert-ckpt", str(ckpt), str(dst), "--ema"])
    out = load_checkpoint(dst)
    assert out["ema_weights"] and out["state_dict"].keys() == trained_state.keys()
    for k, v in out["state_dict"].items():
        name = k.removeprefix(prefix)
        want = shadow[name] if k.startswith(prefix) and name in shadow else trained_state[k]
        assert v.dtype == torch.float32 and torch.equal(v, want), k
    return out["state_dict"]


def test_convert_ema_pretrain(trained, tmp_path, capsys):
    module, ckpt = trained
    assert_converted_ema(ckpt, tmp_path / "ema.safetensors", "model.")
    assert "EMA fp32 weights" in capsys.readouterr().out


def test_convert_ema_controlnet_writes_the_controlnet_ema(trained, tmp_path):
    from omg.lit.controlnet import ControlNetModule

    torch.manual_seed(0)
    module = ControlNetModule(pretrained=str(trained[1]), text_encoder="hash", moc={"d_c": 32, "num_experts": 2},
                              spec=SPEC, ema_decay=0.9, optim={"lr": 1e-2, "warmup_steps": 1})
    ckpt = _fit_steps(module, [_motion_batch(0, "a person walks"), _motion_batch(1, "a person jumps")], tmp_path)
    state = assert_converted_ema(ckpt, tmp_path / "ema.safetensors", "controlnet.")
    # the converted file rebuilds the module with the ControlNet's EMA weights and the frozen model
    loaded = load_module(tmp_path / "ema.safetensors", expect=ControlNetModule)
    shadow = module.ema.state_dict()["shadow"]
    for name, p in loaded.controlnet.named_parameters():
        if name in shadow:
            assert torch.equal(p, shadow[name]), name
    assert_same({k: v for k, v in loaded.state_dict().items()}, state)
    assert_same(load_module(ckpt).state_dict(), state)  # the same as using the .ckpt's EMA directly


class EMAEvaluator(EvaluatorModule):
    """EvaluatorModule with a weight EMA of its trainable ``evaluator``, kept as the diffusion modules keep theirs."""

    def trainable_module(self) -> torch.nn.Module:
        return self.evaluator

    def on_fit_start(self) -> None:
        self.ema = EMA(self.trainable_module(), decay=0.9)

    def optimizer_step(self, *args, **kwargs) -> None:
        super().optimizer_step(*args, **kwargs)
        self.ema.update(self.trainable_module())

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["ema"] = self.ema.state_dict()


def _evaluator_batches():
    return [{**_motion_batch(i, text), "id": f"clip{i}"} for i, text in enumerate(["a person walks", "a person jumps"])]


def test_convert_evaluator_and_its_ema(tmp_path, capsys):
    from omg.lit.evaluator import load_evaluator

    torch.manual_seed(0)
    module = EvaluatorModule(text_encoder="hash", flavor="mini", spec=SPEC, optim={"lr": 1e-3, "warmup_steps": 1})
    ckpt = _fit_steps(module, _evaluator_batches(), tmp_path)
    with pytest.raises(SystemExit):  # EvaluatorModule keeps no EMA: --ema is refused, plainly
        omg(["convert-ckpt", str(ckpt), str(tmp_path / "ema.safetensors"), "--ema"])
    assert "has no EMA weights" in capsys.readouterr().err
    omg(["convert-ckpt", str(ckpt), str(tmp_path / "plain.safetensors")])
    assert_same(load_checkpoint(tmp_path / "plain.safetensors")["state_dict"], module.state_dict())
    assert_same(load_evaluator(tmp_path / "plain.safetensors").state_dict(), module.evaluator.state_dict())

    # an evaluator that keeps an EMA of its trainable `evaluator`: the prefix comes from the module
    torch.manual_seed(0)
    module = EMAEvaluator(text_encoder="hash", flavor="mini", spec=SPEC, optim={"lr": 1e-2, "warmup_steps": 1})
    ckpt = _fit_steps(module, _evaluator_batches(), tmp_path / "ema")
    assert_converted_ema(ckpt, tmp_path / "ema.safetensors", "evaluator.")



def test_settings_groups_load_from_the_plain_mappings_of_earlier_checkpoints(trained, tmp_path):
    """Checkpoints written before the nested settings were typed (omg.settings: ``DiTOverrides``,
    ``MoCOverrides``, ``TextEncoderArgs``, ...) hold them as plain mappings, and new ones still do
    (weights-only loadable): such a checkpoint builds the model it was trained as, and a mapping
    with an unknown key is one line naming it and the accepted ones."""
    from omg.lit.controlnet import ControlNetModule
    from omg.models.controlnet import MoCOverrides
    from omg.text import TextEncoderArgs

    module, path = trained
    saved = torch.load(path, map_location="cpu", weights_only=True)
    assert saved["hyper_parameters"]["dit"] == TINY_DIT  # the set keys only, as the mapping was given
    torch.manual_seed(0)
    cn = ControlNetModule(pretrained=str(path), text_encoder="hash", text_encoder_args=TextEncoderArgs(max_tokens=20),
                          moc=MoCOverrides(d_c=16, num_experts=2), spec=SPEC, ema_decay=0)
    assert cn.hparams["moc"] == {"d_c": 16, "num_experts": 2} and cn.hparams["text_encoder_args"] == {"max_tokens": 20}
    with torch.no_grad():
        for p in cn.controlnet.parameters():
            p.add_(0.02 * torch.randn_like(p))
    # hyper-parameters as a checkpoint of the untyped settings holds them: plain mappings throughout
    hparams = {"pretrained": None, "text_encoder": "hash", "text_encoder_args": {"max_tokens": 20},
               "moc": {"d_c": 16, "num_experts": 2}, "ema_decay": 0.0,
               "base": {"flavor": "mini", "dit": dict(TINY_DIT), "spec": SPEC}, "spec": SPEC}
    old = tmp_path / "old.ckpt"
    torch.save({"state_dict": cn.state_dict(), "hyper_parameters": hparams, "pytorch-lightning_version": L.__version__,
                "module_class": class_path(ControlNetModule)}, old)
    loaded = load_module(old, expect=ControlNetModule)
    assert loaded.config == module.config and loaded.config.n_layers == TINY_DIT["n_layers"]
    assert (loaded.controlnet.config.d_c, loaded.controlnet.config.num_experts) == (16, 2)
    assert loaded.text_encoder.max_tokens == 20
    assert_same(loaded.state_dict(), cn.state_dict())
    # an unknown key of a mapping: one line, the key and the accepted ones
    torch.save({"state_dict": cn.state_dict(), "hyper_parameters": {**hparams, "moc": {"d_cc": 16}},
                "pytorch-lightning_version": L.__version__, "module_class": class_path(ControlNetModule)}, old)
    with pytest.raises(UsageError) as e:
        load_module(old, expect=ControlNetModule)
    said = "model.init_args.moc: unknown key 'd_cc'; did you mean model.init_args.moc.d_c? (accepted keys: d_c, "
    assert "\n" not in str(e.value) and said in str(e.value)
