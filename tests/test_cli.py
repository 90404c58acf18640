"""The `omg` front: help, plugins (entry points), usage errors as one line with exit code 2."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import lightning  # noqa: F401  (imported outside capture: its log handler keeps the stderr it first sees)
import pytest

from helpers import REPO, scratch_registries
from helpers.checkpoints import save_module
from omg.cli import COMMANDS, LIGHTNING, main


def run_omg(*args, env_extra=None, cwd=REPO):
    env = {**os.environ, **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "omg.cli", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=300)


def test_help_lists_every_command(capsys):
    main(["--help"])
    out = capsys.readouterr().out
    for name in [*LIGHTNING, *COMMANDS]:
        assert f"  {name} " in out


def _assert_usage_error(capsys, argv, *fragments):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("omg: error:")
    for fragment in fragments:
        assert fragment in err, err


def test_unknown_command_is_one_line(capsys):
    _assert_usage_error(capsys, ["fitt"], "unknown command 'fitt'", "fit")


@pytest.mark.parametrize("args", [["plugins"], ["--help"]])
def test_stdout_closed_early_ends_quietly(args):
    """`omg plugins | head -1`: the reader is gone before omg writes (a closed pipe, deterministically)."""
    proc = subprocess.Popen([sys.executable, "-m", "omg.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 128 + 13 and err == ""


def test_tool_command_errors_are_one_line(capsys, tmp_path):
    _assert_usage_error(capsys, ["shards", "frobnicate"], "frobnicate", "build")
    _assert_usage_error(capsys, ["shards", "build", "--max_clips", "many"],
                        "max_clips: expected an integer >= 1, got 'many'")
    _assert_usage_error(capsys, ["shards", "build", "--source", "nope", "--out", str(tmp_path)],
                        "unknown data source 'nope'", "synth")
    _assert_usage_error(capsys, ["shards", "inspect", str(tmp_path)], "no manifest.json")


def test_a_tool_subcommand_builds_its_own_parser_only(capsys, monkeypatch, tmp_path):
    """`omg bench NAME` and `omg shards NAME` build NAME's parser alone (each parser reads a function's signature
    and docstring); the command list, `--help` and an unknown name build every one."""
    from omg.tools import args
    from omg.tools.bench import BENCHMARKS

    built = []
    real = args.function_parser
    monkeypatch.setattr(args, "function_parser", lambda function, prog, **kw: built.append(prog) or real(
        function, prog, **kw))
    _assert_usage_error(capsys, ["bench", "plan", "--nope", "1"], "--nope", "omg bench plan --help")
    assert built == ["omg bench plan"]
    _assert_usage_error(capsys, ["shards", "inspect", str(tmp_path)], "no manifest.json")
    assert built[1:] == ["omg shards inspect"]
    built.clear()
    main(["bench"])
    assert built == [f"omg bench {name}" for name in BENCHMARKS] and "timeline" in capsys.readouterr().out
    built.clear()
    _assert_usage_error(capsys, ["bench", "plann"], "invalid choice: 'plann'", "'plan'")
    assert len(built) == len(BENCHMARKS)


PLUGIN = '''
"""A third-party plugin: a 3-joint skeleton and a data source that swings it."""
import numpy as np
from omg.motion import Clip
from omg.registry import DATA_SOURCES, SKELETONS
from omg.skeleton import Skeleton

TOY3 = SKELETONS.register("toy3", Skeleton.from_parents(
    "toy3", [-1, 0, 1], np.array([[0, 1, 0], [0, 0.5, 0], [0, 0.5, 0]]), names=["base", "mid", "tip"]))

@DATA_SOURCES.register("toy-swing")
def toy_swing(input, skeleton, fps, num_clips=4):
    """Pendulum swings of the toy3 arm."""
    for i in range(num_clips):
        T = 30 + i
        angle = 0.3 * np.sin(np.arange(T) / fps * (1 + i))
        rot = np.zeros((T, 3, 4), np.float32)
        rot[..., 0] = 1.0
        rot[:, 1, 0], rot[:, 1, 3] = np.cos(angle / 2), np.sin(angle / 2)
        pos = np.zeros((T, 3, 3), np.float32)
        pos[:, 0, 1] = 1.0
        pos[:, 1] = pos[:, 0] + [0, 0.5, 0]
        pos[:, 2, 0], pos[:, 2, 1] = -0.5 * np.sin(angle), 1.5 + 0.5 * (np.cos(angle) - 1)
        yield Clip(id=f"swing{i}", skeleton=TOY3, fps=fps, positions=pos, rotations=rot,
                   offsets=TOY3.rest_offsets, texts=["an arm swings"], category="toy", source="toy")
'''


@pytest.fixture
def plugin_path(tmp_path) -> Path:
    """An installed plugin distribution (package + dist-info with an omg.plugins entry point)."""
    site = tmp_path / "site"
    (site / "omg_toy_plugin").mkdir(parents=True)
    (site / "omg_toy_plugin" / "__init__.py").write_text(PLUGIN)
    dist = site / "omg_toy_plugin-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: omg-toy-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[omg.plugins]\ntoy = omg_toy_plugin\n")
    return site


@pytest.fixture
def installed_plugin(plugin_path, monkeypatch):
    """The plugin installed in this process, as PYTHONPATH installs it in a new one: its site folder on
    sys.path, where importlib.metadata finds its entry point. omg's own components are registered first,
    and each registry is given back after the test as it was, so the plugin's do not outlive the test."""
    from omg import registry

    scratch_registries(monkeypatch, *registry.ALL.values())
    monkeypatch.setattr(registry, "_plugins_loaded", None)  # entry points read afresh, as at a start
    monkeypatch.syspath_prepend(str(plugin_path))
    yield
    sys.modules.pop("omg_toy_plugin", None)


def test_plugin_components_are_listed_and_selected_by_name_from_yaml(installed_plugin, tmp_path, capsys):
    """In this process (what the commands do, not how a process starts): `omg plugins`, then `omg shards
    build` naming the plugin's source and skeleton from YAML, then one of its options misspelt."""
    main(["plugins"])
    listed = capsys.readouterr().out
    assert "plugins (entry-point group omg.plugins): toy" in listed
    assert "toy3" in listed and "toy-swing" in listed and "Pendulum swings" in listed

    config = tmp_path / "build.yaml"
    config.write_text(textwrap.dedent(f"""
        source: toy-swing
        skeleton: toy3
        representation: maa
        fps: 30
        out: {tmp_path / 'toy_shards'}
        option: {{num_clips: 3}}
    """))
    main(["shards", "build", "--config", str(config)])
    assert "3 clips" in capsys.readouterr().out
    main(["shards", "inspect", str(tmp_path / "toy_shards")])
    inspected = capsys.readouterr().out
    assert "representation maa (24-d) on toy3" in inspected and "3 valid samples" in inspected

    config.write_text(config.read_text() + "colour: blue\n")
    _assert_usage_error(capsys, ["shards", "build", "--config", str(config)], "does not accept option 'colour'")


def test_a_broken_plugin_is_named(tmp_path, plugin_path):
    (plugin_path / "omg_toy_plugin" / "__init__.py").write_text("raise ImportError('needs numpy 9')\n")
    out = run_omg("plugins", env_extra={"PYTHONPATH": os.pathsep.join([str(plugin_path), str(REPO)])})
    assert out.returncode == 2
    assert "omg plugin 'toy' (omg_toy_plugin) failed to load: needs numpy 9" in out.stderr


def test_print_config_resolves_the_mini_config(capsys):
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), "--print_config"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "class_path: omg.lit.PretrainModule" in out and "flavor: mini" in out
    assert "train: shards/mini/human263/train" in out


def test_cpu_threads_follow_the_trainable_work(tmp_path, monkeypatch):
    """One intra-op thread for the small ControlNet recipe (configs/small/controlnet.yaml: 2.3M trainable
    parameters, 26M with the frozen MiniLM, which once got two threads and trained several times slower on
    a busy machine); torch's threads for a genuinely big trainable model; OMP_NUM_THREADS decides when set."""
    import lightning as L
    import torch

    from omg.data.datamodule import MotionDataModule
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import PretrainModule
    from omg.tools.lightning import pick_cpu_threads

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    spec = MotionDataModule(str(REPO / "shards/mini/human263/train"), batch_size=2, num_workers=0).spec
    pre = PretrainModule(flavor="mini", dit={"n_layers": 6, "d_model": 128, "n_heads": 4}, spec=spec, ema_decay=0)
    save_module(pre, tmp_path / "pre.ckpt")
    small = ControlNetModule(pretrained=str(tmp_path / "pre.ckpt"), text_encoder="minilm",
                             moc={"d_c": 64, "num_experts": 4}, spec=spec)
    assert sum(p.numel() for p in small.parameters()) > 25_000_000  # with the frozen MiniLM and DiT
    big = PretrainModule(flavor="mini", dit={"n_layers": 8, "d_model": 512, "n_heads": 8}, spec=spec, ema_decay=0)
    assert sum(p.numel() for p in big.parameters() if p.requires_grad) > 20_000_000
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)

    def threads_for(model) -> int:
        torch.set_num_threads(2)
        pick_cpu_threads(trainer, model)
        return torch.get_num_threads()

    assert threads_for(small) == 1
    assert threads_for(big) == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert threads_for(small) == 2


@pytest.mark.parametrize("extra, line", [
    (["--model.ema_decay", "abc"], "model.init_args.ema_decay: expected a number, got 'abc'"),
    (["--trainer.max-steps", "abc"], "trainer.max_steps: expected an integer, got 'abc'"),
    (["--config", "{bad}"], "trainer.max_steps: expected an integer, got 'abc'"),
    (["--seed_everything", "abc"], "seed_everything: expected true or false or an integer, got 'abc'"),
])
def test_fit_errors_name_the_key(capsys, tmp_path, monkeypatch, extra, line):
    """A bad value for omg fit names its key, from the command line or a config file (each setting
    is checked on its own against the type of its key: jsonargparse's public API only)."""
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    (tmp_path / "bad.yaml").write_text("trainer:\n  max_steps: abc\n")
    extra = [a.format(bad=tmp_path / "bad.yaml") for a in extra]
    _assert_usage_error(capsys, ["fit", "--config", str(REPO / "configs/mini/pretrain.yaml"), *extra], line)
