"""Every YAML under configs/ parses against the real classes and builds its model on meta."""

from __future__ import annotations

import json

import pytest
import torch
import yaml

import omg.callbacks  # noqa: F401  (short class names in configs resolve among imported modules)
import omg.lit  # noqa: F401
from helpers import REPO
from helpers.configs import parse
from omg.data.datamodule import MotionDataModule

CONFIGS = sorted(p for p in (REPO / "configs").rglob("*.yaml"))
FAKE_SPEC = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 30.0, "feature_dim": 263,
             "mean": [0.0] * 263, "std": [1.0] * 263}


QUATVEL_SPEC = {"representation": "quatvel", "skeleton": "smal35", "fps": 20.0, "feature_dim": 245,
                "mean": [0.0] * 245, "std": [1.0] * 245}
# a habit prior config's run directory -> the stage-1 config whose checkpoint it reads
PRIOR_STAGE1 = {"runs/habit_prior": REPO / "configs/habit_vqvae.yaml",
                "runs/mini_habit_prior": REPO / "configs/mini/habit_vqvae.yaml",
                "runs/mini_habit_eval": REPO / "configs/mini/habit_vqvae.yaml",
                "runs/habit_eval": REPO / "configs/habit_vqvae.yaml"}

def maa_spec(skeleton: str, dim: int) -> dict:
    return {"representation": "maa", "skeleton": skeleton, "fps": 20.0, "feature_dim": dim, "mean": [0.0] * dim,
            "std": [1.0] * dim}


def build_model_on_meta(cfg, flavor: str = "mini"):
    module_path, _, cls_name = cfg.model.class_path.rpartition(".")
    cls = getattr(__import__(module_path, fromlist=[cls_name]), cls_name)
    init = {**cfg.model.init_args.as_dict(), "spec": FAKE_SPEC}
    if cls_name == "ControlNetModule":  # no pretrained checkpoint or CLIP weights here: describe the base, hash text
        init.update(base={"flavor": flavor, "dit": None, "spec": FAKE_SPEC}, text_encoder="hash", text_encoder_args={})
    if cls_name == "OmniMotionModule":  # maa on both skeletons; no shards or CLIP weights here: hash text
        init.update(spec=maa_spec("smal35", 216), text_encoder="hash", text_encoder_args={})
    if cls_name == "HabitVQModule":  # habit transfer reads quatvel on SMAL-35
        init["spec"] = QUATVEL_SPEC
    if cls_name == "HabitPriorModule":  # its VQ-VAE checkpoint is not here: the flows of the matching stage-1 config
        from omg.models.habit import CategoryFlows

        vq = build_model_on_meta(parse(PRIOR_STAGE1[cfg.trainer.default_root_dir]))
        with torch.device("meta"):
            return CategoryFlows(len(vq.categories), vq.config)
    with torch.device("meta"):
        return cls(**init)


def test_configs_exist():
    names = {p.relative_to(REPO / "configs").as_posix() for p in CONFIGS}
    for stage in ("pretrain", "controlnet"):
        assert {f"{stage}_{f}.yaml" for f in ("base", "large", "huge", "giant")} | {f"mini/{stage}.yaml"} <= names


def test_controlnet_configs_use_clip_and_name_its_missing_weights(tmp_path):
    from omg.errors import UsageError
    from omg.text import build_text_encoder

    for flavor in ("base", "large", "huge", "giant"):
        cfg = parse(REPO / f"configs/controlnet_{flavor}.yaml")
        args = cfg.model.init_args
        assert args.text_encoder == "clip-vit-l-14" and args.guidance_scale == 4.5 and args.eot_drop == 0.5
        assert (args.optim.lr, args.optim.weight_decay, args.optim.warmup_steps) == (3e-5, 1e-5, 1000)
    with pytest.raises(UsageError, match="pretrained"):
        build_text_encoder("clip-vit-l-14", pretrained=str(tmp_path / "missing.pt"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.relative_to(REPO / "configs").as_posix())
def test_config_parses_and_builds_on_meta(path):
    cfg = parse(path)
    flavor = next((f for f in ("base", "large", "huge", "giant") if f in path.name), "mini")
    model = build_model_on_meta(cfg, flavor)
    n = sum(p.numel() for p in model.parameters())
    assert n > 0 and all(p.is_meta for p in model.parameters())


PAPER_PARAMS = {"base": 88e6, "large": 201e6, "giant": 1.0e9}


def _groups() -> dict[str, tuple[dict[str, type], dict[str, object]]]:
    """configs/mini/X.yaml -> (its model's typed settings groups, values the config sets in them)."""
    from omg.data.paired import CompanionData
    from omg.models.controlnet import MoCOverrides
    from omg.models.dit import DiTOverrides
    from omg.models.evaluator import EvaluatorOverrides
    from omg.models.habit import HabitOverrides
    from omg.models.omgpt import OmniMotionOverrides
    from omg.text import TextEncoderArgs

    return {"pretrain": ({"dit": DiTOverrides}, {}),
            "controlnet": ({"moc": MoCOverrides, "text_encoder_args": TextEncoderArgs}, {"moc.d_c": 64}),
            "evaluator": ({"evaluator": EvaluatorOverrides, "text_encoder_args": TextEncoderArgs}, {}),
            "omgpt": ({"config": OmniMotionOverrides, "text_encoder_args": TextEncoderArgs,
                       "data.human": CompanionData},
                      {"config.latent_shift": True, "data.human.batch_size": 8}),
            "habit_vqvae": ({"habit": HabitOverrides, "text_encoder_args": TextEncoderArgs}, {})}


@pytest.mark.parametrize("name", ["pretrain", "controlnet", "evaluator", "omgpt", "habit_vqvae"])
def test_print_config_lists_every_key_of_the_nested_settings(name, capsys, monkeypatch):
    """The nested settings are typed groups (omg.settings): ``--print_config`` lists each key, unset ones null."""
    import dataclasses
    import sys

    from omg.cli import main

    monkeypatch.setattr(sys, "argv", list(sys.argv))  # `omg fit` sets it for LightningCLI
    with pytest.raises(SystemExit) as e:
        main(["fit", "--config", str(REPO / f"configs/mini/{name}.yaml"), "--print_config"])
    assert e.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    init = printed["model"]["init_args"] | {"data.human": printed["data"]["human"]}  # OmniMotionGPT's human shards
    groups, values = _groups()[name]
    for key, group in groups.items():
        assert list(init[key]) == [f.name for f in dataclasses.fields(group)], key
    for dotted, value in values.items():
        key, _, field = dotted.rpartition(".")
        assert init[key][field] == value, dotted
    unset = [k for key in groups for k, v in init[key].items() if v is None]
    assert unset, "the unset keys are listed too"


@pytest.mark.parametrize("flavor", ["base", "large", "huge", "giant"])
def test_size_configs_differ_only_where_they_must(flavor):
    def flat(d, prefix=""):
        out = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    base = flat(yaml.safe_load((REPO / "configs/pretrain_base.yaml").read_text()))
    this = flat(yaml.safe_load((REPO / f"configs/pretrain_{flavor}.yaml").read_text()))
    differing = {k for k in base.keys() | this.keys() if base.get(k) != this.get(k)}
    allowed = {"model.init_args.flavor", "trainer.strategy", "trainer.strategy.class_path",
               "trainer.strategy.init_args.config", "data.batch_size", "trainer.accumulate_grad_batches",
               "trainer.default_root_dir", "trainer.callbacks"}
    assert differing <= allowed, differing - allowed
    cfg = parse(REPO / f"configs/pretrain_{flavor}.yaml")
    assert cfg.data.batch_size * 8 * cfg.trainer.accumulate_grad_batches == 256  # global batch on one 8-GPU node
    assert cfg.data.max_len <= 300
    n = sum(p.numel() for p in build_model_on_meta(cfg).parameters())
    print(f"{flavor}: {n / 1e6:.1f}M parameters")
    if flavor in PAPER_PARAMS:
        assert abs(n / PAPER_PARAMS[flavor] - 1) <= 0.10, f"{flavor}: {n / 1e6:.1f}M"
    strategy = cfg.trainer.strategy
    if flavor == "base":
        assert strategy == "ddp"
    else:
        assert strategy.class_path.endswith("DeepSpeedStrategy") and cfg.trainer.precision == "bf16-mixed"


def test_deepspeed_config_is_valid_for_deepspeed():
    from deepspeed.runtime.config import DeepSpeedConfig

    config = json.loads((REPO / "configs/deepspeed/zero2.json").read_text())
    # the fields Lightning fills in from the trainer before it hands the config to DeepSpeed
    parsed = DeepSpeedConfig({**config, "train_micro_batch_size_per_gpu": 8, "gradient_accumulation_steps": 4,
                              "gradient_clipping": 1.0})
    assert parsed.zero_optimization_stage == 2 and parsed.train_batch_size == 32
    assert parsed.zero_config.overlap_comm
    with pytest.raises(Exception, match="overlap_comms"):
        DeepSpeedConfig({**config, "train_micro_batch_size_per_gpu": 8,
                         "zero_optimization": {"stage": 2, "overlap_comms": True}})


def _data_sections(cfg: dict):
    """Every (train, min_len, clips) a config trains on: its data and its data.human (OmniMotionGPT's)."""
    for data in (cfg.get("data") or {}, (cfg.get("data") or {}).get("human") or {}):
        if data.get("train") and data.get("clips") != "windows":
            yield data["train"], data.get("min_len", 40), data.get("clips", "auto")


@pytest.mark.parametrize("path", sorted((REPO / "configs/mini").glob("*.yaml")), ids=lambda p: p.name)
def test_mini_whole_clip_configs_train_on_every_committed_clip(path):
    """data.min_len drops whole clips shorter than it: a mini config that trains on whole clips keeps every
    clip of the committed shards, as docs/results/mini_eval.md's figures were measured (mini/evaluator.yaml's old 60
    dropped 5 of 90)."""
    from omg.data.loaders import ClipDataset
    from omg.data.windows import WindowSampler

    cfg = yaml.safe_load(path.read_text())
    model = getattr(omg.lit, (cfg.get("model") or {}).get("class_path", "").split(".")[-1], None)
    for train, min_len, clips in _data_sections(cfg):
        if clips == "auto" and getattr(model, "clip_sampling", "windows") == "windows":
            continue  # windows: a short clip is used whole
        dm = MotionDataModule(str(REPO / train), verify_shards=False)
        samples = ClipDataset.from_shards(dm.train_urls, dm.feature_dim, WindowSampler(1000, 1, "whole")).samples
        assert min(len(s["motion"]) for s in samples) >= min_len, (path.name, train)


def test_small_whole_clip_configs_keep_every_bandai_take():
    """configs/small's whole-clip configs train on every captioned Bandai take, the 13-frame ones too."""
    bandai = REPO.parent / "shared/data/bandai1"
    if not bandai.is_dir():
        pytest.skip("../shared/data/bandai1 is not here")
    frames = []
    for bvh in bandai.glob("*.bvh"):
        head = bvh.read_text(errors="replace").split("MOTION", 1)[1].split("\n", 3)
        count, frame_time = int(head[1].split()[-1]), float(head[2].split()[-1])
        frames.append(int(count * frame_time * 20.0))  # at the shards' 20 fps
    for name in ("controlnet", "evaluator", "eval"):
        cfg = yaml.safe_load((REPO / f"configs/small/{name}.yaml").read_text())
        assert cfg["data"]["min_len"] <= min(frames), name


def test_full_habit_configs_embed_categories_with_bge_and_name_a_missing_snapshot(tmp_path):
    from omg.errors import UsageError
    from omg.lit.habit import HabitVQModule
    from omg.text.bge import CONFIG_KEY

    init = parse(REPO / "configs/habit_vqvae.yaml").model.init_args.as_dict()
    assert init["text_encoder"] == "bge-base-en-v1.5" and init["text_encoder_args"]["model_dir"]
    init["text_encoder_args"] = {"model_dir": str(tmp_path / "no_snapshot")}
    with pytest.raises(UsageError) as error:
        HabitVQModule(**{**init, "flavor": "tiny", "spec": QUATVEL_SPEC})
    assert "\n" not in str(error.value) and CONFIG_KEY in str(error.value)
    offline = {**init, "flavor": "tiny", "spec": QUATVEL_SPEC, "text_encoder": "minilm", "text_encoder_args": None}
    assert HabitVQModule(**offline).category_text.shape[-1] == 384  # the named offline fallback builds
    evaluation = parse(REPO / "configs/habit_eval.yaml")
    callback = evaluation.trainer.callbacks[0].init_args
    assert callback.mode == "paper" and callback.evaluator.startswith("runs/evaluator_habit/")
