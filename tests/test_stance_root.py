"""Stepping the root by the stance foot (``Representation.root_from_stance``, sampling's ``stance_root``):
real walks keep their path, a gliding root is stepped back to what the legs walk, only the root's
horizontal velocity changes, and a sample drawn with it has its planted feet still."""

from __future__ import annotations

import inspect

import pytest
import torch
import yaml

from helpers import REPO
from helpers.checkpoints import save_module
from omg.errors import UsageError
from omg.lit.sampling import SamplingSettings
from omg.motion import get_representation
from omg.motion.humanml3d263 import FEET_LEFT, FEET_RIGHT, HumanML3D263

FPS = 20.0
TAKES = ("walk_normal_001", "walk-left_normal_001", "walk-right_normal_001", "run_normal_001")


@pytest.fixture(scope="session")
def real_features() -> dict[str, torch.Tensor]:
    """HumanML3D-263 features (T, 263) of real Bandai-Namco takes at 20 fps."""
    from helpers import SHARED_MOTION
    from omg.io.read import read_motion
    from omg.retarget import retarget

    folder = SHARED_MOTION / "human" / "bandai1"
    if not folder.is_dir():
        pytest.skip(f"real motion data not found at {folder} (the shared/ folder beside the checkout)")
    rep = HumanML3D263()
    return {name: torch.from_numpy(rep.encode(retarget(read_motion(folder / f"dataset-1_{name}.bvh"), "smpl22",
                                                         fps=FPS))[0]).double() for name in TAKES}


def path(features: torch.Tensor) -> torch.Tensor:
    """The root's horizontal displacement over the clip (2,)."""
    root = HumanML3D263().decode(features)[..., 0, :]
    return root[..., -1, [0, 2]] - root[..., 0, [0, 2]]


def stance_slide(features: torch.Tensor) -> float:
    """Median world speed (m/s) of the slowest planted foot joint: 0 when planted feet stay planted."""
    joints = HumanML3D263().decode(features)[:, list(FEET_LEFT + FEET_RIGHT)]  # (T, 4, 3)
    speed = (joints[1:, :, [0, 2]] - joints[:-1, :, [0, 2]]).norm(dim=-1) * FPS  # (T-1, 4)
    contact = features[:, 259:263] > 0.5
    planted = contact[1:] & contact[:-1]
    speed = speed.masked_fill(~planted, float("inf")).min(-1).values
    return float(speed[planted.any(-1)].median())


@pytest.mark.parametrize("name", TAKES)
def test_real_motion_keeps_its_path(real_features, name):
    """A captured take's planted feet are (nearly) still: stepping its root by them moves it by little."""
    f = real_features[name]
    rep = HumanML3D263()
    stepped = rep.root_from_stance(f)
    before, after = path(f), path(stepped)
    assert before.norm() > 1.5  # metres: the take travels
    assert (after - before).norm() < 0.06 * before.norm()
    assert torch.equal(rep.root_from_stance(f, 0.0), f)


@pytest.mark.parametrize("name", TAKES[:3])
def test_a_gliding_root_is_stepped_back_to_the_legs(real_features, name):
    """Twice the root velocity with the same legs is a body that glides over sliding feet: stepping the
    root by the stance foot gives back the take's own path and planted feet."""
    f = real_features[name]
    glide = f.clone()
    glide[:, 1:3] *= 2
    rep = HumanML3D263()
    assert stance_slide(glide) > 5 * stance_slide(f)  # the glide slides its feet
    stepped = rep.root_from_stance(glide)
    assert (path(stepped) - path(f)).norm() < 0.1 * path(f).norm()
    assert stance_slide(stepped) < 1e-6  # the stance foot is still, exactly
    half = rep.root_from_stance(glide, 0.5)  # strength: that much of the way
    assert torch.allclose(half[:, 1:3], (glide[:, 1:3] + stepped[:, 1:3]) / 2)


def test_only_the_root_velocity_changes(real_features):
    f = real_features["walk_normal_001"].clone()
    f[:, 1:3] *= 1.5
    stepped = HumanML3D263().root_from_stance(f)
    changed = (stepped != f).any(0).nonzero().squeeze(1).tolist()
    assert changed == [1, 2]
    assert torch.equal(stepped[-1], f[-1])  # the last frame's velocity leads nowhere
    no_contact = f.clone()
    no_contact[:, 259:263] = 0
    assert torch.equal(HumanML3D263().root_from_stance(no_contact), no_contact)  # nothing planted: nothing to step by


@pytest.mark.parametrize("name", ["maa", "quatvel"])
def test_representations_without_it_refuse_in_one_line(name):
    from omg.skeleton import SMAL35

    rep = get_representation(name, SMAL35)
    assert not rep.stance_root
    with pytest.raises(UsageError, match="cannot step its root by the stance foot") as e:
        rep.root_from_stance(torch.zeros(4, rep.dim))
    assert "\n" not in str(e.value)


def tiny_pretrain(stance_root: float = 0.0):
    """An untrained tiny model whose estimates walk: feet planted (contact mean 1), the root gliding
    forward (velocity mean 0.05 m/frame), and random weights around that."""
    from helpers import TINY_DIT
    from helpers.checkpoints import SPEC
    from omg.lit.pretrain import PretrainModule

    mean = list(SPEC["mean"])
    mean[2], mean[259:263] = 0.05, [1.0] * 4
    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit=TINY_DIT, spec={**SPEC, "mean": mean}, ema_decay=0,
                            sampling={"stance_root": stance_root})
    with torch.no_grad():
        for p in module.parameters():
            p.add_(torch.randn_like(p) * 0.05)  # the zero-initialised output layer too
    return module


def test_a_sample_has_its_planted_feet_still():
    """The last x̂0 a sampler returns is stepped too: where the sample says a foot is planted, the
    stance foot does not move, whatever the (untrained) network made of the root."""
    module = tiny_pretrain().eval()
    plain = module.sample(None, [24, 16], SamplingSettings(steps=4, seed=1))
    stepped = module.sample(None, [24, 16], SamplingSettings(steps=4, seed=1, stance_root=1.0))
    assert torch.equal(module.sample(None, [24, 16], SamplingSettings(steps=4, seed=1, stance_root=0.0)), plain)
    default = tiny_pretrain(stance_root=1.0).eval()
    assert torch.equal(default.sample(None, [24, 16], SamplingSettings(steps=4, seed=1)), stepped)
    assert not torch.equal(stepped, plain)
    for row, frames in enumerate((24, 16)):
        f, g = stepped[row, :frames].double(), plain[row, :frames].double()
        assert (f[1:, 259:263] > 0.5).logical_and(f[:-1, 259:263] > 0.5).any(-1).float().mean() > 0.5
        assert stance_slide(g) > 0.1  # m/s: the plain sample slides
        assert stance_slide(f) < 1e-3


def test_the_option_is_checked_where_it_is_given():
    with pytest.raises(UsageError, match=r"model.sampling.stance_root must be in \[0, 1\]"):
        tiny_pretrain(stance_root=1.5)
    with pytest.raises(UsageError, match=r"^stance_root must be in \[0, 1\]"):  # one check, wherever it is given
        tiny_pretrain().sample(None, [8], SamplingSettings(steps=1, stance_root=-0.1))
    from omg.callbacks import EvalCallback, RenderCallback

    with pytest.raises(UsageError, match=r"EvalCallback.stance_root must be in \[0, 1\]"):
        EvalCallback(metrics=["foot_skating"], stance_root=2.0)
    with pytest.raises(UsageError, match=r"RenderCallback.stance_root must be in \[0, 1\]"):
        RenderCallback(stance_root=float("nan"))
    unset = EvalCallback(metrics=["foot_skating"]).sampling
    assert unset.stance_root is None and "stance_root" not in unset.report()  # unset: other families as before
    assert EvalCallback(metrics=["foot_skating"], stance_root=1.0).sampling.stance_root == 1.0
    # smoothing alike: the callbacks' own, else the model's (a checkpoint's sampling.smoothing)
    with pytest.raises(UsageError, match=r"EvalCallback.smoothing must be a number of frames in \[0, 10\]"):
        EvalCallback(metrics=["foot_skating"], smoothing=11.0)
    assert unset.smoothing is None and RenderCallback(smoothing=0.0).sampling.smoothing == 0.0


def test_generate_records_it(tmp_path):
    from omg.tools.generate import generate

    module = tiny_pretrain()
    ckpt = tmp_path / "pre.ckpt"
    save_module(module, ckpt)
    settings = generate(unconditional=True, ckpt=ckpt, num_samples=1, length=1.0, steps=2, preview=False,
                        stance_root=1.0, out=tmp_path / "out")
    assert settings["stance_root"] == 1.0
    from omg.generation.registry import generator_for

    card = generator_for(module).generation_card()
    assert "stance_root" in card.options


def test_the_small_recipe_samples_with_it_and_the_paper_configs_do_not():
    """Contact-aware sampling is omg's: the small real-data recipe turns it on (measured in
    docs/results/small_recipe.md), OMG's own configs leave the module's default, off."""
    small = yaml.safe_load((REPO / "configs/small/controlnet.yaml").read_text())
    assert small["model"]["init_args"]["sampling"] == {"stance_root": 1.0, "smoothing": 1.0}
    papers = sorted(REPO.glob("configs/controlnet*.yaml")) + sorted(REPO.glob("configs/pretrain*.yaml"))
    assert papers
    for path in papers:
        assert "stance_root" not in path.read_text() and "sampling:" not in path.read_text(), path
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import PretrainModule

    for cls in (ControlNetModule, PretrainModule):
        assert inspect.signature(cls).parameters["sampling"].default.stance_root == 0.0
