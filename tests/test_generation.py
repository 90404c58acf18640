"""Generation as its own floor: each family's adapter found by module class (a plugin family's too), the
declared tensor-level sampler the callbacks call, and ``omg generate --option KEY=VALUE`` checked against the
generation card."""

from __future__ import annotations

import json

import lightning as L
import numpy as np
import pytest
import torch

from helpers import TINY_DIT
from helpers.checkpoints import SPEC, save_module
from omg.errors import UsageError
from omg.generation.habit import HabitGenerator
from omg.generation.omg import OmgGenerator
from omg.generation.omgpt import OmniMotionGenerator
from omg.generation.protocol import GenerationCard, Generator, ModuleGenerator
from omg.generation.registry import generator_for, module_key, register_generator
from omg.lit.controlnet import ControlNetModule
from omg.lit.habit import HabitPriorModule, HabitVQModule
from omg.lit.omgpt import OmniMotionModule
from omg.lit.pretrain import PretrainModule
from omg.lit.sampling import Sampler, SamplingSettings, sampler_of
from omg.registry import GENERATORS


def bare(cls: type):
    """An instance of ``cls`` without its constructor: the registry looks at the class only."""
    return cls.__new__(cls)


@pytest.mark.parametrize("cls, adapter", [(PretrainModule, OmgGenerator), (ControlNetModule, OmgGenerator),
                                          (OmniMotionModule, OmniMotionGenerator), (HabitVQModule, HabitGenerator),
                                          (HabitPriorModule, HabitGenerator)])
def test_the_registry_finds_each_familys_adapter(cls, adapter):
    generator = generator_for(bare(cls))
    assert type(generator) is adapter and isinstance(generator, Generator)
    # the family modules hold training only: no generation method is left on them
    assert not any(hasattr(cls, name) for name in ("generation_card", "read_source", "generation_settings",
                                                   "transfer_motions", "species_condition"))


def test_omnimotiongpt_human_source_chain_lives_outside_its_module():
    """OmniMotionModule holds training and ``translate``; the retrieval and human-source chain, and the sampler the
    callbacks call, are ``omg.lit.human_source``'s, found for the module by its class."""
    import omg.lit.omgpt
    from omg.lit.human_source import HumanSource, OmniMotionSampler, human_source_of

    chain = ("sample", "check_sampling", "text_conditional", "human_motion", "check_human_source", "retrieval_clips",
             "exclude_from_retrieval", "retrieve_human", "retrieved", "human_generator")
    assert [name for name in chain if hasattr(OmniMotionModule, name)] == []
    assert [name for name in ("generate_human", "read_retrieval_bank", "HumanSource", "OmniMotionSampler")
            if hasattr(omg.lit.omgpt, name)] == []
    assert callable(OmniMotionModule.translate)  # the model's own forward stays the module's
    module = bare(OmniMotionModule)
    assert not isinstance(module, Sampler)
    sampler = sampler_of(module, "EvalCallback")
    assert type(sampler) is OmniMotionSampler and isinstance(sampler, Sampler) and sampler.module is module
    assert type(sampler.humans) is HumanSource and sampler.humans is human_source_of(module)  # one per module
    assert human_source_of(bare(OmniMotionModule)) is not sampler.humans


def test_a_module_without_an_adapter_is_one_line():
    class Trainer(L.LightningModule):
        pass

    with pytest.raises(UsageError) as e:
        generator_for(Trainer(), "run.ckpt")
    assert str(e.value) == f"run.ckpt holds a {module_key(Trainer)} checkpoint, which generates no motion"


def test_a_plugin_family_registers_its_adapter_and_a_subclass_its_own():
    class MyModule(L.LightningModule):
        pass

    class MyDiffusion(PretrainModule):  # an OMG subclass generates like OMG until it registers its own
        pass

    assert type(generator_for(bare(MyDiffusion))) is OmgGenerator

    class MyGenerator(ModuleGenerator):
        def generation_card(self) -> GenerationCard:
            return GenerationCard(family="mine", skeleton="smpl22", representation="humanml3d263", fps=20.0,
                                  inputs=("text",))

    try:
        register_generator(MyModule)(MyGenerator)
        register_generator(MyDiffusion)(MyGenerator)
        assert type(generator_for(MyModule())) is MyGenerator
        assert type(generator_for(bare(MyDiffusion))) is MyGenerator
        with pytest.raises(UsageError, match="a mine checkpoint takes no source motion"):
            generator_for(MyModule()).read_source("clip.bvh")
    finally:
        for cls in (MyModule, MyDiffusion):
            GENERATORS._entries.pop(module_key(cls), None)


def test_the_callbacks_call_the_declared_sampler_and_refuse_a_module_without_one():
    from omg.callbacks import EvalCallback, RenderCallback
    from omg.callbacks.eval import check_generative

    callback = EvalCallback(metrics=["foot_skating"], steps=3, sampler="dpmpp", use_ema=False)
    seen = []

    class Spy(L.LightningModule):  # a module that declares the protocol
        text_conditional = True

        def sample(self, texts, lengths, settings=None):
            seen.append((texts, settings))
            return torch.zeros(len(lengths), 4, 2)

        def check_sampling(self, settings, key):
            pass

    assert isinstance(Spy(), Sampler)
    callback.generate(Spy(), ["a person walks"], torch.tensor([4]), seed=5)
    assert seen == [(["a person walks"], SamplingSettings(steps=3, sampler="dpmpp", seed=5, use_ema=False,
                                                          key="EvalCallback"))]
    for key, what in (("EvalCallback", callback.sampling), ("RenderCallback", RenderCallback().sampling)):
        with pytest.raises(UsageError) as e:
            check_generative(torch.nn.Linear(1, 1), key, what)
        assert str(e.value).startswith(f"{key} needs a model that samples motion") and "\n" not in str(e.value)
        assert "Linear has none" in str(e.value)
    with pytest.raises(UsageError, match="--ckpt needs a model that samples motion"):
        sampler_of(object(), "--ckpt")


def test_sampling_settings_are_checked_once_where_they_are_made():
    with pytest.raises(UsageError, match=r"^EvalCallback.stance_root must be in \[0, 1\]"):
        SamplingSettings(stance_root=1.5, key="EvalCallback")
    with pytest.raises(UsageError, match=r"^steps must be an integer >= 1, got 0"):
        SamplingSettings(steps=0)
    with pytest.raises(UsageError, match="unknown sampler 'nope'"):
        SamplingSettings(sampler="nope")
    assert SamplingSettings(seeds=[1, 2]).seeds == (1, 2)  # frozen: a tuple
    assert SamplingSettings().report() == {"steps": 200, "guidance": None, "use_ema": True, "sampler": "ddim"}


@pytest.fixture(scope="module")
def pretrain_ckpt(tmp_path_factory):
    mean = list(SPEC["mean"])
    mean[2], mean[259:263] = 0.05, [1.0] * 4  # estimates that walk on planted feet: stance_root has work to do
    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec={**SPEC, "mean": mean}, ema_decay=0)
    with torch.no_grad():
        for p in module.parameters():
            p.add_(torch.randn_like(p) * 0.05)  # the zero-initialised output layer too
    ckpt = tmp_path_factory.mktemp("gen") / "pre.ckpt"
    save_module(module, ckpt)
    return ckpt


GENERATE = ["generate", "--unconditional", "--num_samples", "1", "--length", "0.5", "--steps", "2", "--no_preview"]


def test_option_is_checked_against_the_card(pretrain_ckpt, tmp_path, capsys):
    from omg.cli import main

    for option, message in (("bogus=1", f"{pretrain_ckpt} (PretrainModule) takes no option bogus; its options: "
                                        "stance_root, smoothing"),
                            ("stance_root=2", "--option stance_root=2: give a number in [0, 1]"),
                            ("smoothing=11", "--option smoothing=11: give a number in [0, 10]"),
                            ("smoothing=nan", "--option smoothing=nan: give a number in [0, 10]"),
                            ("stance_root", "--option 'stance_root': give KEY=VALUE, e.g. --option stance_root=VALUE")):
        with pytest.raises(SystemExit) as e:
            main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--option", option, "--out", str(tmp_path / "bad")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err == f"omg: error: {message}\n", err
        assert not (tmp_path / "bad").exists()
    # --option stance_root=V is --stance_root V: the same motion, the same settings
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--option", "stance_root=1", "--out", str(tmp_path / "o")])
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--stance_root", "1", "--out", str(tmp_path / "f")])
    for name in ("sample_000.features.npy", "sample_000.joints.npy", "sample_000.bvh"):
        assert (tmp_path / "o" / name).read_bytes() == (tmp_path / "f" / name).read_bytes(), name
    settings = json.loads((tmp_path / "o/generation.json").read_text())
    assert settings["stance_root"] == 1.0 and settings["module"] == "PretrainModule"
    plain = np.load(tmp_path / "f/sample_000.features.npy")
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--out", str(tmp_path / "p")])
    assert not np.array_equal(np.load(tmp_path / "p/sample_000.features.npy"), plain)  # the option did something
    assert "smoothing" not in settings  # off unless given
    # --option smoothing=F: the same noise, every estimate smoothed over time, recorded
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--option", "smoothing=2", "--length", "2", "--out",
          str(tmp_path / "s")])
    main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--length", "2", "--out", str(tmp_path / "r")])
    assert json.loads((tmp_path / "s/generation.json").read_text())["smoothing"] == 2.0
    rough, smooth = (np.load(tmp_path / f"{d}/sample_000.joints.npy") for d in ("r", "s"))
    assert np.abs(np.diff(smooth, n=3, axis=0)).mean() < 0.5 * np.abs(np.diff(rough, n=3, axis=0)).mean()


def test_a_checkpoints_own_smoothing_is_its_default(pretrain_ckpt, tmp_path):
    """``model.sampling.smoothing`` (set in a config, kept in the checkpoint, as stance_root): `omg generate` smooths by
    it where no --option says otherwise, records it, and the card shows it as the option's default; --option
    smoothing=0 turns it off; a checkpoint without it (every earlier one) generates as before."""
    from omg.cli import main
    from omg.lit.checkpoint import load_module

    ckpt = torch.load(pretrain_ckpt, map_location="cpu", weights_only=False)
    hparams, written = dict(ckpt["hyper_parameters"]), {}
    sampling = hparams.pop("sampling")
    # one with model.sampling.smoothing 2; one as every earlier checkpoint is: stance_root flat, no smoothing
    for name, changed in (("own", {"sampling": {**sampling, "smoothing": 2.0}}),
                          ("earlier", {"stance_root": sampling["stance_root"]})):
        written[name] = tmp_path / f"{name}.ckpt"
        torch.save({**ckpt, "hyper_parameters": {**hparams, **changed}}, written[name])
    assert generator_for(load_module(written["own"])).generation_card().option_ranges["smoothing"].default == 2.0
    runs = {"own": (written["own"],), "asked": (pretrain_ckpt, "--option", "smoothing=2"),
            "off": (written["own"], "--option", "smoothing=0"), "plain": (pretrain_ckpt,),
            "earlier": (written["earlier"],)}
    for out, (path, *option) in runs.items():
        main([*GENERATE, "--length", "2", "--ckpt", str(path), *option, "--out", str(tmp_path / out)])
    features = {out: (tmp_path / out / "sample_000.features.npy").read_bytes() for out in runs}
    assert features["own"] == features["asked"] != features["plain"] == features["off"] == features["earlier"]
    settings = {out: json.loads((tmp_path / out / "generation.json").read_text()) for out in runs}
    assert settings["own"]["smoothing"] == 2.0 and "smoothing" not in settings["off"]


def test_a_prior_checkpoint_is_refused_by_a_family_without_one(pretrain_ckpt, tmp_path, capsys):
    from omg.cli import main

    with pytest.raises(SystemExit) as e:
        main([*GENERATE, "--ckpt", str(pretrain_ckpt), "--prior_ckpt", str(pretrain_ckpt), "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err == f"omg: error: --prior_ckpt: {pretrain_ckpt} (PretrainModule) takes no prior " \
                                         "checkpoint\n"


# -- progress -------------------------------------------------------------------------------


def test_generate_reports_each_batch_and_its_steps_and_samples_as_unwatched(pretrain_ckpt):
    from dataclasses import replace

    from omg.generation.progress import Progress
    from omg.generation.protocol import GenerationRequest
    from omg.lit.checkpoint import load_module

    generator = generator_for(load_module(pretrain_ckpt))
    heard = []
    request = GenerationRequest(prompts=None, frames=10, num_samples=3, steps=2, batch_size=2, seed=5)
    watched = generator.generate(replace(request, progress=heard.append))
    assert heard == [Progress(0, 2, 3, 0, 2), Progress(0, 2, 3, 1, 2), Progress(0, 2, 3, 2, 2),
                     Progress(0, 2, 3, 2, 2, finished=True),
                     Progress(2, 1, 3, 0, 2), Progress(2, 1, 3, 1, 2), Progress(2, 1, 3, 2, 2),
                     Progress(2, 1, 3, 2, 2, finished=True)]
    assert [p.done for p in heard[3::4]] == [2, 3] and heard[0].motions == "motions 1-2 of 3"
    for a, b in zip(watched, generator.generate(request)):
        assert np.array_equal(a.features, b.features)


def test_the_clock_times_what_is_left_at_the_measured_seconds_per_step():
    from omg.generation.progress import Progress, ProgressClock

    now = [0.0]
    clock = ProgressClock(seconds_per_step=0.5, clock=lambda: now[0])
    assert clock.time_left() is None and clock.steps_left() is None  # nothing reported yet
    now[0] = 1.0
    clock(Progress(0, 2, 3, 0, 4))  # 4 steps of this batch and 4 of the last (one motion) left
    assert clock.steps_left() == 8 and clock.time_left() == 4.0  # at an earlier call's 0.5 s a step
    now[0] = 3.0
    clock(Progress(0, 2, 3, 1, 4))
    assert clock.seconds_per_step == 2.0 and clock.time_left() == 14.0  # 7 steps at this call's own rate
    now[0] = 4.0
    assert clock.time_left() == 13.0 and clock.elapsed() == 4.0  # a second since the step
    now[0] = 9.0
    clock(Progress(0, 2, 3, 4, 4))
    clock(Progress(0, 2, 3, 4, 4, finished=True))
    now[0] = 10.0
    clock(Progress(2, 1, 3, 0, 4))  # the next batch: the previous one's rate until its first step
    assert clock.steps_left() == 4 and clock.time_left() == 4 * 2.0
    now[0] = 10.5
    clock(Progress(2, 1, 3, 1, 4))
    assert clock.seconds_per_step == 0.5 and clock.time_left() == 1.5
    # a family without sampler steps: each motion is one step
    bare = ProgressClock(clock=lambda: now[0])
    bare(Progress(0, 1, 3))
    assert bare.time_left() is None  # no rate known yet
    now[0] = 13.5
    bare(Progress(0, 1, 3, finished=True))
    assert bare.steps_left() == 2 and bare.time_left() == 6.0


def test_a_terminal_gets_one_line_redrawn_in_place():
    import io

    from omg.generation.progress import Progress
    from omg.tools.generate import ProgressLine

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    now, stream = [0.0], Terminal()
    line = ProgressLine(stream, clock=lambda: now[0])
    assert line.live
    line(Progress(0, 2, 3, 0, 100))
    for step in range(1, 7):  # a step each 0.04 s: drawn each 0.1 s or more, at steps 3 and 6
        now[0] = 0.04 * step
        line(Progress(0, 2, 3, step, 100))
    now[0] = 70.0
    line(Progress(0, 2, 3, 100, 100, finished=True))  # a batch's end and start are always drawn
    made = "motions 1-2 of 3 made in 100 steps, 1m10s elapsed, about 4s left"
    line(Progress(2, 1, 3, 0, 100))
    line.close()
    assert stream.getvalue().split("\r")[1:] == [
        "motions 1-2 of 3: step 0 of 100, 0s elapsed",
        "motions 1-2 of 3: step 3 of 100, 0s elapsed, about 8s left",  # 197 steps left at 0.04 s
        "motions 1-2 of 3: step 6 of 100, 0s elapsed, about 8s left",
        made,
        "motion 3 of 3: step 0 of 100, 1m10s elapsed, about 4s left".ljust(len(made)) + "\n"]  # covers the longer
    assert "\r" not in (plain := io.StringIO()).getvalue() and not ProgressLine(plain).live


def test_generate_writes_a_line_per_batch_when_redirected_and_none_with_no_progress(pretrain_ckpt, tmp_path, capsys):
    import re

    from omg.cli import main

    run = ["generate", "--unconditional", "--num_samples", "3", "--batch_size", "2", "--length", "0.5", "--steps", "3",
           "--no_preview", "--ckpt", str(pretrain_ckpt)]
    capsys.readouterr()
    main([*run, "--out", str(tmp_path / "a")])
    out, err = capsys.readouterr()
    assert out == f"wrote 3 motions of 10 frames (0.5 s at 20 fps) to {tmp_path / 'a'}\n"  # stdout: the result alone
    lines = err.splitlines()
    assert len(lines) == 2 and "\r" not in err, err
    assert re.fullmatch(r"motions 1-2 of 3 made in 3 steps, \w+ elapsed, about \w+ left", lines[0]), lines
    assert re.fullmatch(r"motion 3 of 3 made in 3 steps, \w+ elapsed", lines[1]), lines
    main([*run, "--no_progress", "--out", str(tmp_path / "b")])
    assert capsys.readouterr().err == ""
    for name in ("sample_000.features.npy", "sample_002.features.npy"):  # watched or not, the same motions
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
