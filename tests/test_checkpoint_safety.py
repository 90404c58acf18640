"""Reading a checkpoint never runs code from it, and a bad ``--ckpt_path`` is one line.

A crafted checkpoint's pickle calls whatever its ``__reduce__`` names when it is unpickled; here
that creates a marker file. Every entry point that reads checkpoints must refuse such a file
with one UsageError line (exit 2 from the CLI) before the marker exists. The same holds for a
``.safetensors`` file whose metadata names a module to import, and for an evaluator class_path.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file
from torch.serialization import get_unsafe_globals_in_checkpoint

from helpers import REPO, TINY_DIT, TINY_DIT_ARG
from helpers.checkpoints import SPEC, save_module, write_zero2_checkpoint, zero_tensor_bytes
from helpers.forked import OmgProcess
from omg.cli import main as omg
from omg.errors import UsageError
from omg.lit.checkpoint import LIGHTNING_SAFE_GLOBALS, convert, inspect_checkpoint, load_checkpoint, load_module
from omg.lit.pretrain import PretrainModule

pytestmark = pytest.mark.xdist_group("checkpoint_safety")  # the tests share the `runs` fixture's checkpoints

MINI = REPO / "shards/mini/human263"


class Payload:
    """Unpickling this object calls ``open(path, "w")``: a crafted checkpoint would call os.system."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return open, (self.path, "w")


@pytest.fixture(scope="session")
def tiny() -> PretrainModule:
    torch.manual_seed(0)
    return PretrainModule(flavor="mini", dit=TINY_DIT, spec=SPEC)


def _lightning_dict(module: PretrainModule) -> dict:
    return {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "module_class": "omg.lit.pretrain.PretrainModule", "global_step": 1}


def _crafted(kind: str, module: PretrainModule, root: Path, marker: Path) -> Path:
    """A checkpoint of ``module`` whose pickles run code: in a Lightning .ckpt, in the Lightning
    state DeepSpeed keeps in its model-states file, or in DeepSpeed's optimizer-states file (which
    only DeepSpeed's own zero_to_fp32 loader reads)."""
    if kind == "lightning":
        torch.save({**_lightning_dict(module), "callbacks": {"x": Payload(marker)}}, root / "evil.ckpt")
        return root / "evil.ckpt"
    client = {k: v for k, v in _lightning_dict(module).items() if k != "state_dict"}
    if kind == "deepspeed-client-state":
        client["loops"] = {"x": Payload(marker)}
    write_zero2_checkpoint(module, client, root / "evil_ds")
    if kind == "deepspeed-optimizer-states":
        file = next((root / "evil_ds/checkpoint").glob("*_optim_states.pt"))
        states = torch.load(file, weights_only=False)  # our own harmless file
        torch.save({**states, "extra": Payload(marker)}, file)
    return root / "evil_ds"


def _controlnet(src: Path, out: Path):
    from omg.lit.controlnet import ControlNetModule

    return ControlNetModule(pretrained=str(src), text_encoder="hash")


def _eval_callback_evaluator(src: Path, out: Path):
    from omg.evaluation import build_evaluator  # what EvalCallback calls with its `evaluator` path

    return build_evaluator(str(src))


ENTRY_POINTS = {
    "load_checkpoint": lambda src, out: load_checkpoint(src),
    "load_module": lambda src, out: load_module(src),
    "convert": lambda src, out: convert(src, out / "x.safetensors", ema=True),
    "ControlNetModule(pretrained=...)": _controlnet,
    "EvalCallback evaluator": _eval_callback_evaluator,
    "omg convert-ckpt": lambda src, out: omg(["convert-ckpt", str(src), str(out / "x.safetensors")]),
    "omg generate --ckpt": lambda src, out: omg(["generate", "--unconditional", "--ckpt", str(src),
                                                 "--steps", "1", "--out", str(out / "gen")]),
    "omg fit --ckpt_path": lambda src, out: omg(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"),
                                                 f"--data.train={MINI}/train", f"--data.val={MINI}/val",
                                                 f"--trainer.default_root_dir={out}", "--trainer.max_steps=1",
                                                 f"--trainer.callbacks.dirpath={out}/ck", f"--ckpt_path={src}"]),
}


@pytest.mark.parametrize("kind", ["lightning", "deepspeed-client-state", "deepspeed-optimizer-states"])
def test_no_entry_point_runs_a_checkpoints_code(kind, tiny, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    for i, (name, entry) in enumerate(ENTRY_POINTS.items()):
        out, marker = tmp_path / str(i), tmp_path / f"marker{i}"
        out.mkdir()
        src = _crafted(kind, tiny, out, marker)
        capsys.readouterr()
        if name.startswith("omg "):
            with pytest.raises(SystemExit) as exit:
                entry(src, out)
            err = capsys.readouterr().err.strip()
            assert exit.value.code == 2 and err.startswith("omg: error: ") and "\n" not in err, (name, err)
        else:
            with pytest.raises(UsageError) as error:
                entry(src, out)
            err = str(error.value)
            assert "\n" not in err, (name, err)
        assert "refused" in err and "could run code" in err, (name, err)
        assert not marker.exists(), f"{name} ran the checkpoint's code"


def test_a_safetensors_file_cannot_make_omg_import_a_module(tiny, tmp_path, capsys, monkeypatch):
    marker = tmp_path / "imported"
    (tmp_path / "omg_test_crafted_module.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nimport lightning\n\nclass Module(lightning.LightningModule):\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    torch.save(_lightning_dict(tiny), tmp_path / "good.ckpt")
    convert(tmp_path / "good.ckpt", tmp_path / "good.safetensors")
    from safetensors import safe_open

    with safe_open(tmp_path / "good.safetensors", "pt") as f:
        metadata = f.metadata()
    crafted = tmp_path / "crafted.safetensors"
    save_file(load_file(tmp_path / "good.safetensors"), crafted,
              {**metadata, "module_class": json.dumps("omg_test_crafted_module.Module")})

    with pytest.raises(UsageError, match=r"omg imports only its own LightningModules .* and omg_test_crafted_module"):
        load_module(crafted)
    for argv in (["generate", "--unconditional", "--ckpt", str(crafted), "--out", str(tmp_path / "gen")],
                 ["convert-ckpt", str(crafted), str(tmp_path / "out.safetensors")]):
        with pytest.raises(SystemExit) as exit:
            omg(argv)
        err = capsys.readouterr().err.strip()
        assert exit.value.code == 2 and "omg_test_crafted_module.Module" in err and "\n" not in err
    assert not marker.exists() and "omg_test_crafted_module" not in sys.modules
    assert isinstance(load_module(tmp_path / "good.safetensors"), PretrainModule)  # omg's own classes still load


class TinyEvaluator(torch.nn.Module):
    def __init__(self, dim: int = 4):
        super().__init__()
        self.proj = torch.nn.Linear(dim, dim)

    def encode_text(self, texts):
        return torch.zeros(len(texts), 4)

    def encode_motion(self, motion, mask=None):
        return torch.zeros(len(motion), 4)


def test_an_evaluator_class_path_is_checked_before_it_is_called(tmp_path):
    from omg.evaluation import build_evaluator

    marker = tmp_path / "called"
    with pytest.raises(UsageError, match="builtins.open is not a text-motion evaluator"):
        build_evaluator({"class_path": "builtins.open", "init_args": {"file": str(marker), "mode": "w"}})
    assert not marker.exists()
    with pytest.raises(UsageError, match="evaluator.class_path: 'omg.nothing.Here' cannot be imported"):
        build_evaluator({"class_path": "omg.nothing.Here"})
    assert isinstance(build_evaluator({"class_path": f"{__name__}.TinyEvaluator", "init_args": {"dim": 4}}),
                      TinyEvaluator)


# -- real checkpoints and --ckpt_path ------------------------------------------------------------

COMMON = [f"--data.train={MINI}/train", f"--data.val={MINI}/val", "--data.batch_size=4", "--data.max_len=30",
          "--data.min_len=20", "--data.num_workers=0", "--trainer.enable_progress_bar=false",
          "--trainer.enable_model_summary=false", "--trainer.val_check_interval=1000",
          "--trainer.callbacks.every_n_train_steps=1"]
PRETRAIN = ["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *COMMON,
            TINY_DIT_ARG]


def _fit(*argv: str) -> None:
    saved = list(sys.argv)  # omg.cli sets sys.argv for LightningCLI
    try:
        omg(list(argv))
    finally:
        sys.argv[:] = saved


@pytest.fixture(scope="session")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Checkpoints written by `omg fit` (LightningCLI) for the three modules: 2 pretraining steps,
    1 ControlNet and 1 evaluator step (the hash text encoder)."""
    root = tmp_path_factory.mktemp("runs")
    _fit(*PRETRAIN, "--trainer.max_steps=2", f"--trainer.default_root_dir={root}/pre",
         f"--trainer.callbacks.dirpath={root}/pre/ck")
    _fit("fit", "--config", str(REPO / "configs/mini/controlnet.yaml"), *COMMON, "--trainer.max_steps=1",
         f"--trainer.default_root_dir={root}/cn", f"--trainer.callbacks.dirpath={root}/cn/ck",
         f"--model.init_args.pretrained={root}/pre/ck/last.ckpt", "--model.init_args.text_encoder=hash",
         '--model.init_args.moc={"d_c": 32, "num_experts": 2}')
    _fit("fit", "--config", str(REPO / "configs/mini/evaluator.yaml"), *COMMON, "--trainer.max_steps=1",
         f"--trainer.default_root_dir={root}/ev", f"--trainer.callbacks.dirpath={root}/ev/ck",
         "--model.init_args.text_encoder=hash")
    return {"pre": root / "pre/ck", "cn": root / "cn/ck/last.ckpt", "ev": root / "ev/ck/last.ckpt"}


def test_real_checkpoints_hold_only_allow_listed_globals(runs):
    """The allow-list of the weights-only loads is exactly what `omg fit` checkpoints need: nothing."""
    checkpoints = {runs["pre"] / "last.ckpt": "omg.lit.PretrainModule", runs["cn"]: "omg.lit.ControlNetModule",
                   runs["ev"]: "omg.lit.EvaluatorModule"}
    for path, cls in checkpoints.items():
        assert set(get_unsafe_globals_in_checkpoint(path)) <= set(LIGHTNING_SAFE_GLOBALS) == set(), path
        assert inspect_checkpoint(path)["module_class"] == cls


def _fit_error(capsys, *argv: str) -> str:
    capsys.readouterr()
    saved = list(sys.argv)
    try:
        with pytest.raises(SystemExit) as exit:
            omg(list(argv))
    finally:
        sys.argv[:] = saved
    err = capsys.readouterr().err.strip()
    assert exit.value.code == 2 and err.startswith("omg: error: ") and "\n" not in err, err[-3000:]
    return err


def test_a_controlnet_written_by_omg_fit_loads_without_its_pretrained_file(runs, tmp_path):
    """A ControlNet checkpoint holds the frozen model's description (``base``) as well as its weights, so it loads
    where the stage-1 checkpoint it was fine-tuned on is gone; LightningCLI hands the module its own config to save,
    in which that description is unset."""
    ckpt = torch.load(runs["cn"], weights_only=True)
    assert ckpt["hyper_parameters"]["base"]["flavor"] == "mini"
    ckpt["hyper_parameters"]["pretrained"] = str(tmp_path / "gone.ckpt")
    torch.save(ckpt, tmp_path / "moved.ckpt")
    moved, there = load_module(tmp_path / "moved.ckpt"), load_module(runs["cn"])
    assert all(torch.equal(a, b) for a, b in zip(moved.state_dict().values(), there.state_dict().values()))


def test_ckpt_path_of_another_class_or_unreadable_is_one_line(runs, tiny, tmp_path, capsys):
    pretrain = [*PRETRAIN, "--trainer.max_steps=3", f"--trainer.default_root_dir={tmp_path}",
                f"--trainer.callbacks.dirpath={tmp_path}/ck"]
    for other in ("cn", "ev"):
        err = _fit_error(capsys, *pretrain, f"--ckpt_path={runs[other]}")
        assert "checkpoint, but the config's model is omg.lit.pretrain.PretrainModule" in err
        assert ("ControlNetModule" if other == "cn" else "EvaluatorModule") in err
    err = _fit_error(capsys, "fit", "--config", str(REPO / "configs/mini/controlnet.yaml"), *COMMON,
                     f"--trainer.default_root_dir={tmp_path}", f"--ckpt_path={runs['pre'] / 'last.ckpt'}",
                     f"--model.init_args.pretrained={runs['pre'] / 'last.ckpt'}", "--model.init_args.text_encoder=hash")
    assert "holds a omg.lit.PretrainModule checkpoint" in err and "model.init_args.pretrained" in err

    last = runs["pre"] / "last.ckpt"
    zero_tensor_bytes(last, tmp_path / "zeroed.ckpt")
    (tmp_path / "truncated.ckpt").write_bytes(last.read_bytes()[:5000])
    (tmp_path / "random.ckpt").write_bytes(os.urandom(5000))
    torch.save({"weights": torch.ones(2)}, tmp_path / "weights.pt")
    convert(last, tmp_path / "model.safetensors")
    write_zero2_checkpoint(tiny, {k: v for k, v in _lightning_dict(tiny).items() if k != "state_dict"}, tmp_path / "ds")
    cases = {"missing.ckpt": "missing.ckpt: no such file", "zeroed.ckpt": "zeroed.ckpt is corrupt",
             "truncated.ckpt": "truncated.ckpt is corrupt", "random.ckpt": "random.ckpt is not a checkpoint",
             "weights.pt": "not a Lightning checkpoint", "model.safetensors": "cannot restore a run",
             "ds": "is a DeepSpeed checkpoint directory, which only a DeepSpeed run restores"}
    for name, message in cases.items():
        err = _fit_error(capsys, *pretrain, f"--ckpt_path={tmp_path / name}")
        assert f"--ckpt_path {tmp_path}" in err and message in err, err
    assert not (tmp_path / "ck").exists()  # nothing trained


def _dead_pid() -> int:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(done.stdout)


def test_a_new_run_over_an_earlier_last_ckpt_says_so(runs, tmp_path):
    """A run started (not resumed) where an earlier run left last.ckpt writes last-v1.ckpt, which a
    ControlNet config reading last.ckpt would never see: one warning names both files and what to do."""
    ck = tmp_path / "ck"
    shutil.copytree(runs["pre"], ck)
    old = (ck / "last.ckpt").read_bytes()
    with pytest.warns(UserWarning) as warned:
        _fit(*PRETRAIN, "--trainer.max_steps=1", f"--trainer.default_root_dir={tmp_path}",
             f"--trainer.callbacks.dirpath={ck}")
    said = [str(w.message) for w in warned if "earlier run" in str(w.message)]
    assert said == [f"{ck / 'last.ckpt'} is from an earlier run: this run writes last-v1.ckpt beside it, and a config "
                    "that reads last.ckpt (model.init_args.pretrained) keeps reading the old one; resume it with "
                    "--ckpt_path last, or give this run its own trainer.default_root_dir"]
    assert (ck / "last-v1.ckpt").is_file() and (ck / "last.ckpt").read_bytes() == old  # what it said happened
    with warnings.catch_warnings(record=True) as resumed:  # resuming goes on writing the run's own last file
        warnings.simplefilter("always")
        _fit(*PRETRAIN, "--trainer.max_steps=2", f"--trainer.default_root_dir={tmp_path}",
             f"--trainer.callbacks.dirpath={ck}", "--ckpt_path=last")
    assert not [w for w in resumed if "earlier run" in str(w.message)]
    assert not (ck / "last-v2.ckpt").exists()


def test_resume_last_falls_back_to_the_newest_readable_checkpoint(runs, tmp_path, capsys):
    ck = tmp_path / "ck"
    shutil.copytree(runs["pre"], ck)
    step2 = ck / "epoch=0-step=2.ckpt"
    assert step2.exists() and (ck / "last.ckpt").exists()
    (ck / "last.ckpt").write_bytes((ck / "last.ckpt").read_bytes()[:-4096])  # a torn write
    pid = _dead_pid()
    stale = [ck / f".last.{pid}.tmp.ckpt", tmp_path / "version_0" / f".eval.{pid}.tmp.json"]
    stale[1].parent.mkdir()
    for path in stale:
        path.write_bytes(b"partial")
    keep = [ck / f".last.{os.getpid()}.tmp.ckpt", ck / "notes.tmp"]  # a live writer's, and not omg's
    for path in keep:
        path.write_bytes(b"x")

    restored = []
    handler = logging.Handler()
    handler.emit = lambda record: restored.append(record.getMessage())
    logging.getLogger("lightning.pytorch").addHandler(handler)
    try:
        with pytest.warns(UserWarning, match=r"--ckpt_path last: .*last.ckpt is corrupt.*resuming from .*step=2.ckpt"):
            _fit(*PRETRAIN, "--trainer.max_steps=3", f"--trainer.default_root_dir={tmp_path}",
                 f"--trainer.callbacks.dirpath={ck}", "--ckpt_path=last")
    finally:
        logging.getLogger("lightning.pytorch").removeHandler(handler)
    assert any("Restoring states from the checkpoint path at" in m and m.endswith("step=2.ckpt") for m in restored)
    # last-v1.ckpt: the copy's state names another dir
    newest = max(ck.glob("last*.ckpt"), key=lambda p: p.stat().st_mtime)
    assert torch.load(newest, weights_only=True)["global_step"] == 3
    assert not any(p.exists() for p in stale) and all(p.exists() for p in keep)
    assert not [p for p in ck.iterdir() if p.name.startswith(".") and p not in keep]  # atomic writes left nothing

    for path in ck.glob("*.ckpt"):  # nothing readable left: one line, no training
        path.write_bytes(path.read_bytes()[:1000])
    err = _fit_error(capsys, *PRETRAIN, "--trainer.max_steps=5", f"--trainer.default_root_dir={tmp_path}",
                     f"--trainer.callbacks.dirpath={ck}", "--ckpt_path=last")
    assert "--ckpt_path last: " in err and "is corrupt" in err and f"no other checkpoint in {ck} reads" in err


KILLED_SAVE = """
import os, signal, sys, torch
from omg.callbacks.checkpoint import AtomicCheckpointIO

def save_and_die(obj, f):
    open(f, "wb").write(b"PK\\x03\\x04 half a checkpoint")
    os.kill(os.getpid(), signal.SIGKILL)

torch.save = save_and_die
AtomicCheckpointIO().save_checkpoint({"state_dict": {}}, sys.argv[1])
"""


def test_a_killed_checkpoint_write_keeps_the_old_file_and_its_temp_file_is_cleaned(tmp_path):
    from omg.callbacks.checkpoint import AtomicCheckpointIO, remove_stale_temp_files

    last = tmp_path / "ck" / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"state_dict": {"w": torch.ones(3)}, "global_step": 7}, last)
    assert [p.name for p in last.parent.iterdir()] == ["last.ckpt"]
    script = tmp_path / "killed_save.py"  # a real process, forked from the tests' preloaded server (helpers.forked)
    script.write_text(KILLED_SAVE)
    assert OmgProcess([str(last)], script=script).wait(timeout=120) == -9
    temp = [p for p in last.parent.iterdir() if p != last]
    assert len(temp) == 1 and temp[0].name.startswith(".last.") and temp[0].name.endswith(".tmp.ckpt")
    assert torch.load(last, weights_only=True)["global_step"] == 7  # the old checkpoint, whole
    assert remove_stale_temp_files([last.parent]) == temp and [p.name for p in last.parent.iterdir()] == ["last.ckpt"]


def test_a_checkpoint_of_the_wrong_kind_says_what_it_is(tiny, tmp_path, capsys):
    """A bare state dict is named as one (not "the model needs its data spec"), and an evaluator
    checkpoint given as a ControlNet's pretrained model names both classes (not a state-dict mismatch)."""
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.evaluator import EvaluatorModule

    torch.save({"state_dict": tiny.state_dict()}, tmp_path / "bare.ckpt")
    for argv in (["generate", "--unconditional", "--ckpt", str(tmp_path / "bare.ckpt"), "--out", str(tmp_path / "g")],
                 ["convert-ckpt", str(tmp_path / "bare.ckpt"), str(tmp_path / "bare.safetensors")]):
        with pytest.raises(SystemExit) as exit:
            omg(argv)
        err = capsys.readouterr().err.strip()
        assert exit.value.code == 2 and "\n" not in err, err
        assert err.startswith(f"omg: error: {tmp_path / 'bare.ckpt'} is a bare state dict: it holds weights without "
                              "the module's hyper-parameters or class") and "expected a Lightning .ckpt file" in err
    assert not (tmp_path / "g").exists() and not (tmp_path / "bare.safetensors").exists()

    evaluator = EvaluatorModule(text_encoder="hash", flavor="mini", spec=SPEC)
    save_module(evaluator, tmp_path / "evaluator.ckpt")
    with pytest.raises(UsageError) as error:
        ControlNetModule(pretrained=str(tmp_path / "evaluator.ckpt"), text_encoder="hash")
    assert str(error.value) == (f"model.init_args.pretrained: {tmp_path / 'evaluator.ckpt'} holds a "
                                "omg.lit.evaluator.EvaluatorModule checkpoint, where a omg.lit.pretrain.PretrainModule "
                                "(stage-1) or omg.lit.controlnet.ControlNetModule checkpoint is expected")
