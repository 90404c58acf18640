"""The papers' numbers, read as a user gets them (the configs as `omg fit` parses them, the modules they build, the
defaults): OMG's budgets, MoC sizes and 200 DDIM steps (Sec. 3.2, 4.1); OmniMotionGPT's loss weights (§3.1-3.2,
Appendix C), training on C̃^a and implementation details (§5); Behave Your Motion's stage-1 loss mix, 2e-4 -> 1e-5
step schedule and evaluation protocol. Each assertion names the section; changing a number fails its test."""

from __future__ import annotations

import dataclasses
import inspect

import lightning as L
import pytest
import torch
import yaml

from helpers import REPO
from helpers.configs import parse
from helpers.habit import CATEGORIES, QUATVEL
from helpers.omgpt import MINI, human_batch, tiny_module
from helpers.omgpt import data as _data
from omg.data.datamodule import MotionDataModule
from omg.lit.habit import HabitVQModule
from omg.lit.omgpt import OmniMotionModule
from omg.losses import masked_smooth_l1

OMGPT_WEIGHTS = {"jrec": 1.0, "clip": 1.0, "trec": 1.0, "cons": 0.1, "cross_clip": 1.0, "ee": 100.0,
                 "translation": 1.0}
HABIT_MIX = {"loss": {"alpha": 0.5, "beta": 0.02}, "optim": {"lr": 2e-4, "lr_after": 1e-5, "lr_switch": 0.5}}


def _defaults(cls) -> dict:
    return {k: p.default for k, p in inspect.signature(cls).parameters.items()}


def _group_defaults(cls, group: str) -> dict:
    return dataclasses.asdict(_defaults(cls)[group])


def test_omnimotiongpt_total_loss_is_the_papers_weighted_sum():
    """L = Σ_d (L_jrec + 1 L_CLIP + 1 L_trec + 1 L_translation) + 0.1 L_cons + 1 L_CLIP~ + 100 L_ee, by default."""
    torch.manual_seed(0)
    animal = _data(MINI / "animal_maa/train")
    module = tiny_module(animal.spec)
    assert module.weights == OMGPT_WEIGHTS
    assert {f"{k}_weight": v for k, v in OMGPT_WEIGHTS.items()} == _group_defaults(OmniMotionModule, "loss")
    batch, human = next(iter(animal.train_dataloader())), human_batch()
    out = module.losses(batch, human)
    parts = {k: out[f"{d}/{k}"] for d in ("human", "animal") for k in ("jrec", "clip", "trec", "translation")}
    assert all(v > 0 for v in parts.values()) and all(out[f"cross/{k}"] > 0 for k in ("cons", "cross_clip", "ee"))
    expected = sum(out[f"{d}/{k}"] * OMGPT_WEIGHTS[k] for d in ("human", "animal")
                   for k in ("jrec", "clip", "trec", "translation"))
    expected = expected + sum(out[f"cross/{k}"] * OMGPT_WEIGHTS[k] for k in ("cons", "cross_clip", "ee"))
    torch.testing.assert_close(out["loss"], expected)
    # a weight moves the total by exactly its term: the end-effector velocity term at 100
    module.weights = {**OMGPT_WEIGHTS, "ee": 0.0}
    torch.manual_seed(0)
    without = module.losses(batch, human)
    torch.testing.assert_close(out["loss"] - without["loss"], 100.0 * out["cross/ee"], rtol=1e-4, atol=1e-5)


@pytest.fixture(scope="session")
def quatvel():
    return MotionDataModule(str(QUATVEL / "train"), batch_size=8, max_len=64, min_len=64,
                            clips="windows", batches_per_epoch=8, num_workers=0, shuffle_buffer=32,
                            verify_shards=False)


@pytest.mark.parametrize("order", ["flow_prior", "kl_then_flows"])
def test_habit_stage1_loss_is_the_papers_mix(quatvel, order):
    """L = smooth L1 (motion) + 0.5 · smooth L1 (velocity channels) + 0.02 · commitment, by default; the
    VQ-VAE of the paper's order (its encoders pretrained under their flows) has no KL term, omg's earlier
    order adds kl_weight · KL(q || N(0, I))."""
    assert all(HABIT_MIX[g].items() <= _group_defaults(HabitVQModule, g).items() for g in HABIT_MIX)
    torch.manual_seed(0)
    module = HabitVQModule(CATEGORIES, order={"habit_order": order}, flavor="tiny", spec=quatvel.spec).eval()
    batch = next(iter(quatvel.train_dataloader()))
    out, recon, _ = module.losses(batch)
    v = module.num_joints * 4  # quatvel: 35 quaternions, then the joint velocities
    mask = batch["mask"].float()
    torch.testing.assert_close(out["motion"], masked_smooth_l1(recon, batch["motion"], mask))
    torch.testing.assert_close(out["velocity"], masked_smooth_l1(recon[..., v:], batch["motion"][..., v:], mask))
    expected = out["motion"] + 0.5 * out["velocity"] + 0.02 * out["commitment"]
    if order == "kl_then_flows":
        expected = expected + module.loss.kl_weight * out["kl"]
    else:
        assert "kl" not in out
    torch.testing.assert_close(out["loss"], expected)
    assert out["velocity"] > 0 and out["commitment"] > 0


class _LearningRates(L.Callback):
    def __init__(self):
        self.seen: list[float] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.seen.append(trainer.optimizers[0].param_groups[0]["lr"])


@pytest.mark.parametrize("order, steps, expected", [
    ("kl_then_flows", 8, [2e-4] * 4 + [1e-5] * 4),
    ("flow_prior", 10, [2e-4] * 2 + [2e-4] * 4 + [1e-5] * 4),  # 2 habit pretraining steps at lr, then the VQ-VAE's 8
])
def test_habit_learning_rate_steps_from_2e4_to_1e5_for_the_second_half(quatvel, tmp_path, order, steps, expected):
    torch.manual_seed(0)
    module = HabitVQModule(CATEGORIES, order={"habit_order": order}, flavor="tiny", spec=quatvel.spec)
    rates = _LearningRates()
    trainer = L.Trainer(accelerator="cpu", max_steps=steps, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(tmp_path),
                        limit_val_batches=0, callbacks=[rates])
    trainer.fit(module, datamodule=quatvel)
    assert rates.seen == pytest.approx(expected)


def test_omgpt_config_has_the_papers_numbers():
    cfg = parse(REPO / "configs/omgpt.yaml")
    args = cfg.model.init_args
    assert {k: args.loss[f"{k}_weight"] for k in OMGPT_WEIGHTS} == OMGPT_WEIGHTS  # §3.1-3.2, Appendix C
    optim = args.optim
    assert (optim.lr, tuple(optim.betas), optim.weight_decay, args.ema_decay) == (1e-4, (0.9, 0.999), 0.0, 0.99)  # §5
    assert (args.text_encoder, args.text_feature, args.flavor) == ("clip-vit-l-14", "projected", "paper")
    assert cfg.trainer.max_steps == 30000 and cfg.data.batch_size == cfg.data.human.batch_size == 256
    # whole clips of the papers' lengths: AnimalML3D 10-196, HumanML3D 20-196 frames
    assert (cfg.data.clips, cfg.data.min_len, cfg.data.max_len) == ("whole", 10, 196)
    human = cfg.data.human
    assert (human.clips, human.min_len, human.max_len) == ("whole", 20, 196)


def test_habit_configs_have_the_papers_numbers():
    from omg.models.habit import HabitConfig

    cfg = parse(REPO / "configs/habit_vqvae.yaml")
    args = cfg.model.init_args
    assert {g: {k: args[g][k] for k in HABIT_MIX[g]} for g in HABIT_MIX} == HABIT_MIX
    codebook = args.codebook
    assert (codebook.quantizer, codebook.code_reset, args.condition_decoder, codebook.ema_decay) == ("soft", True,
                                                                                                     False, 0.99)
    # the paper's order: each category's habit encoder pretrained under its flow prior, then the VQ-VAE's
    # 200K iterations on the pretrained encoders
    assert args.order.habit_order == _defaults(HabitVQModule)["order"].habit_order == "flow_prior"
    assert parse(REPO / "configs/mini/habit_vqvae.yaml").model.init_args.order.habit_order == "flow_prior"  # the mini
    assert cfg.trainer.max_steps - int(args.order.habit_fraction * cfg.trainer.max_steps) == 200000
    assert cfg.data.batch_size == 32 and cfg.data.max_len == cfg.data.min_len == 64
    base = HabitConfig.from_name(args.flavor)
    assert (base.num_codes, base.down_t, base.dilation_growth, base.width) == (512, 2, 3, 512)
    assert (base.habit_layers, base.habit_width, base.habit_heads) == (4, 512, 8)
    prior = parse(REPO / "configs/habit_prior.yaml")
    assert prior.model.init_args.optim.lr == 2e-4 and prior.data.batch_size == 32


def _omgpt_switches(path) -> dict:
    """The three switches omg adds to OmniMotionGPT, as the config resolves them (defaults included)."""
    from omg.models.omgpt import OmniMotionConfig

    args = parse(path).model.init_args
    config = OmniMotionConfig.from_name(args.flavor, **(args.config or {}))
    standardize = args.get("standardize", _defaults(OmniMotionModule)["standardize"])
    return {"latent_shift": config.latent_shift, "root_velocity": config.root_velocity, "standardize": standardize}


def test_omgpt_paper_config_is_the_paper_and_the_variant_is_named():
    """configs/omgpt.yaml: unshifted D_t, absolute root translation, raw maa (§3.1); omg's variant is its own
    overlay (configs/omgpt_variant.yaml) with all three on, and the mini run says it trains the variant."""
    assert _omgpt_switches(REPO / "configs/omgpt.yaml") == dict.fromkeys(("latent_shift", "root_velocity",
                                                                         "standardize"), False)
    variant = dict.fromkeys(("latent_shift", "root_velocity", "standardize"), True)
    assert _omgpt_switches(REPO / "configs/omgpt_variant.yaml") == variant
    assert _omgpt_switches(REPO / "configs/mini/omgpt.yaml") == variant
    mini = yaml.safe_load((REPO / "configs/mini/omgpt.yaml").read_text())["model"]["init_args"]
    assert {*mini["config"], "standardize"} >= set(variant) and mini["standardize"]  # said, not inherited


# -- OMG (Liang et al., CVPR 2024) ------------------------------------------------------------------------------
SIZES = ("base", "large", "huge", "giant")
OMG_SPEC = {"representation": "humanml3d263", "skeleton": "smpl22", "fps": 20.0, "feature_dim": 263,
            "mean": [0.0] * 263, "std": [1.0] * 263}


@pytest.mark.parametrize("size", SIZES)
def test_omg_pretraining_configs_have_the_papers_budget(size):
    """configs/pretrain_{size}.yaml as `omg fit` parses it: 1M iterations of AdamW at 1e-4 (Sec. 4.1); the global
    batch of 256 on one 8-GPU node and the windows l ~ U[1, 300] are tests/test_configs.py's and
    tests/test_datamodule.py's."""
    cfg = parse(REPO / f"configs/pretrain_{size}.yaml")
    assert cfg.trainer.max_steps == 1_000_000, f"{size}: OMG Sec. 4.1 pretrains for 1M iterations"
    assert cfg.model.init_args.optim.lr == 1e-4, f"{size}: OMG Sec. 4.1: AdamW, learning rate 1e-4"


def _controlnet_on_meta(cfg):
    """The ControlNetModule a config builds, on meta, on a described mini base (no checkpoint or CLIP here)."""
    from omg.lit.controlnet import ControlNetModule

    init = {**cfg.model.init_args.as_dict(), "spec": OMG_SPEC, "text_encoder": "hash", "text_encoder_args": {},
            "base": {"flavor": "mini", "dit": None, "spec": OMG_SPEC}}
    with torch.device("meta"):
        return ControlNetModule(**init)


@pytest.mark.parametrize("size", SIZES)
def test_omg_controlnet_configs_have_the_papers_budget_and_controllers(size):
    """configs/controlnet_{size}.yaml: batch 64, 500 epochs of HumanML3D's 23,384 training clips (Sec. 4.1), and the
    MoC the module builds from it: K = 12 experts of width d_c = 256, γ = 24, β = 0.25 (Sec. 3.2, 4.1)."""
    cfg = parse(REPO / f"configs/controlnet_{size}.yaml")
    per_step = cfg.data.batch_size * 8 * cfg.trainer.accumulate_grad_batches  # on one 8-GPU node
    assert per_step == 64, f"{size}: OMG Sec. 4.1: batch size 64, got {per_step}"
    assert cfg.trainer.max_steps == 23384 * 500 // 64, f"{size}: OMG Sec. 4.1: 500 epochs of 23,384 clips at batch 64"
    clips_per_epoch = cfg.data.batches_per_epoch * cfg.data.batch_size * 8
    assert abs(clips_per_epoch - 23384) <= per_step / 2, f"{size}: an epoch is one pass of HumanML3D's 23,384 clips"
    moc = _controlnet_on_meta(cfg).controlnet.config
    assert (moc.num_experts, moc.d_c, moc.gamma, moc.beta) == (12, 256, 24.0, 0.25), \
        f"{size}: OMG Sec. 4.1: K = 12, d_c = 256, γ = 24, β = 0.25; got {moc}"
    assert moc.experts == "moc" and moc.token_masks and moc.zero_init and moc.wiring == "per_layer"  # the full model


def test_omg_samples_with_200_ddim_steps_by_default():
    """OMG reports DDIM sampling with 200 steps (Sec. 4.1): what `omg generate`, `omg serve` and the evaluation
    use when no --steps / --sampler is given (the card's default, and the steps the sampler is run with)."""
    from omg.callbacks.eval import EvalCallback
    from omg.generation.protocol import GenerationRequest
    from omg.generation.registry import generator_for
    from omg.lit.pretrain import PretrainModule

    torch.manual_seed(0)
    module = PretrainModule(flavor="mini", dit={"n_layers": 1, "d_model": 16, "n_heads": 2}, spec=OMG_SPEC,
                            ema_decay=0).eval()
    generator = generator_for(module)
    assert generator.generation_card().default_steps == 200, "OMG Sec. 4.1: 200 DDIM steps"
    runs, sample = [], module.sample

    def recorded(texts, lengths, settings, **watch):  # the real sampler, its steps and sampler noted
        runs.append((settings.steps, settings.sampler))
        return sample(texts, lengths, settings, **watch)

    module.sample = recorded
    request = GenerationRequest(prompts=None, frames=2)
    generator.generate(request)
    assert runs == [(200, "ddim")], f"OMG Sec. 4.1: DDIM, 200 steps; sampled with {runs}"
    settings = generator.generation_settings(request)
    assert (settings["steps"], settings["sampler"]) == (200, "ddim")
    evaluation = _defaults(EvalCallback)  # `omg test`'s text-to-motion evaluation
    assert (evaluation["steps"], evaluation["sampler"]) == (200, "ddim"), "OMG Sec. 4.1: DDIM, 200 steps"


# -- OmniMotionGPT (Yang et al. 2023) ---------------------------------------------------------------------------
def test_omnimotiongpt_cross_domain_terms_read_the_caption_about_the_animal():
    """§3.2: the cross-domain terms (L_cons through D_t^a, L_CLIP~) read C̃^a, the human caption with its subject
    replaced by the paired animal's species, not the human caption C^h."""
    from omg.text.omgpt import to_animal

    assert to_animal("A man walks forward and he waves his arm", "dog") == "A dog walks forward and it waves its arm"
    torch.manual_seed(0)
    animal = _data(MINI / "animal_maa/train")
    module = tiny_module(animal.spec)
    batch, human = next(iter(animal.train_dataloader())), human_batch()
    read, sentence = [], module.sentence

    def recorded(texts):  # the real sentence features, the captions they were taken of noted
        read.append(list(texts))
        return sentence(texts)

    module.sentence = recorded
    module.losses(batch, human)
    assert read[:2] == [list(human["text"]), list(batch["text"])] and len(read) == 3  # C^h, C^a, then the cross
    pairs = [batch["category"][i % len(batch["text"])] for i in range(len(human["text"]))]  # human i, animal i mod B_a
    expected = [to_animal(text, species) if text else "" for text, species in zip(human["text"], pairs)]
    assert any(expected) and read[2] != list(human["text"]), "OmniMotionGPT §3.2 trains the cross terms on C̃^a"
    assert read[2] == expected, "OmniMotionGPT §3.2: C̃^a, the subject replaced by the paired animal"


def test_omnimotiongpt_paper_config_builds_the_papers_widths():
    """§5: joint transformers of width 16 and 2 layers, temporal ones of width 256 and 2 layers, pooling l = 4, the
    latent decoder D_t of width 256 and 4 layers: configs/omgpt.yaml as `omg fit` parses it, in the module it builds."""
    from omg.lit.omgpt import OmniMotionModule

    def maa(skeleton: str, dim: int) -> dict:
        return {"representation": "maa", "skeleton": skeleton, "fps": 20.0, "feature_dim": dim, "mean": [0.0] * dim,
                "std": [1.0] * dim}

    init = {**parse(REPO / "configs/omgpt.yaml").model.init_args.as_dict(), "spec": maa("smal35", 216),
            "text_encoder": "hash", "text_encoder_args": {}}
    with torch.device("meta"):
        module = OmniMotionModule(**init)
    c = module.config
    widths = {"joint": (c.joint_dim, c.joint_layers), "temporal": (c.temporal_dim, c.temporal_layers),
              "latent": (c.latent_dim, c.latent_layers), "pool": c.pool, "max_frames": c.max_frames}
    assert widths == {"joint": (16, 2), "temporal": (256, 2), "latent": (256, 4), "pool": 4, "max_frames": 196}, \
        f"OmniMotionGPT §5's networks, got {widths}"
    for domain in ("human", "animal"):
        decoder = getattr(module.model, domain)["text_decoder"]
        assert decoder.embed.out_features == 256 and len(decoder.blocks.layers) == 4, domain  # D_t as built


# -- Behave Your Motion: the habit evaluation -------------------------------------------------------------------
def test_habit_evaluation_protocol_is_the_papers():
    """configs/habit_eval.yaml as `omg test` parses it, and HabitEvalCallback's defaults: a category is a downstream
    (transfer) target with >= 5 real samples, Diversity over 300 pairs (Sec. 4.4.1), on the VQ-VAE's 64-frame crops."""
    from omg.callbacks.habit import HabitEvalCallback

    cfg = parse(REPO / "configs/habit_eval.yaml")
    callback = next(c for c in cfg.trainer.callbacks if c.class_path.endswith("HabitEvalCallback")).init_args
    defaults = _defaults(HabitEvalCallback)
    for key, paper in (("min_samples", 5), ("diversity_pairs", 300)):
        assert callback[key] == defaults[key] == paper, f"Behave Your Motion Sec. 4.4.1: {key} = {paper}"
    crop = callback.crop_len or cfg.data.max_len
    assert crop == parse(REPO / "configs/habit_vqvae.yaml").data.max_len == 64, "the VQ-VAE's 64-frame crops"
