"""OMG stage 1: unconditional MotionDiT pretraining on unlabeled motion.

Loss (MDM-style geometric terms on positions decoded from the representation):
    L = L_simple + vel_weight · L_vel + foot_weight · L_foot
where L_simple is the λ_t-weighted x̂0 MSE in normalised feature space, L_vel compares joint
velocities of x̂0 and x0, and L_foot penalises the velocity of feet that are in contact in x0.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from omg.diffusion import Denoiser, Diffusion, StepProgress
from omg.errors import UsageError
from omg.lit.base import OmgModule, OptimSettings, check_weights, modes_restored
from omg.lit.control import Control, smoothed, steered
from omg.lit.sampling import SamplingDefaults, SamplingSettings, check_smoothing, check_stance_root
from omg.lit.timeline import chains_denoiser, check_timeline, compose_chains, timeline_denoiser
from omg.losses import GeometricLoss
from omg.models.checkpointing import checkpoint_each
from omg.models.dit import DiTConfig, DiTOverrides, MotionDiT
from omg.motion import DataSpec, get_representation, length_mask
from omg.registry import SAMPLERS
from omg.settings import set_fields
from omg.skeleton import get_skeleton

log = logging.getLogger(__name__)


def fresh_noise_seed(seed: int, step: int, rank: int) -> int:
    """The noise-RNG seed of a rank that a checkpoint written on fewer ranks has no state for:
    a function of (run seed, step, rank), so it differs from every rank's seed at step 0
    (``seed + rank``) and a resumed run is reproducible."""
    return int(np.random.SeedSequence([seed, step, rank]).generate_state(1, np.uint64)[0])


@dataclass(frozen=True)
class DiffusionLossWeights:
    """The weights of the diffusion stages' geometric terms: L = L_simple + vel_weight · L_vel + foot_weight ·
    L_foot (OMG/MDM: 30 each)."""

    vel_weight: float = 30.0
    foot_weight: float = 30.0

    def __post_init__(self) -> None:
        check_weights(self)


class MotionDiffusionModule(OmgModule):
    """What the diffusion stages share: the x̂0-predicting MotionDiT, its losses, optimizer and
    schedule, the weight EMA and sampling (``sample``). Subclasses save their own
    hyper-parameters and say what they train (``trainable_module``) and how they denoise."""

    text_conditional = False  # whether ``sample`` follows texts
    clip_sampling = "windows"  # what data.clips=auto cuts from clips (omg.data.windows)

    def __init__(self, flavor: str, dit: DiTOverrides | dict | None, spec: DataSpec | dict | None, *,
                 optim: OptimSettings | dict | None, loss: DiffusionLossWeights | dict | None, ema_decay: float,
                 loss_weighting: str, activation_checkpointing: bool,
                 sampling: SamplingDefaults | dict | None = None):
        super().__init__()
        # checked here, when the module is built: the EMA would refuse it only at fit start
        if not 0 <= ema_decay < 1:
            raise UsageError(f"model.ema_decay must be in [0, 1) (0: no EMA), got {ema_decay!r}")
        self.optim, self.loss = self.value_group("optim", optim), self.value_group("loss", loss)
        self.spec = DataSpec.coerce(spec)
        self.ema_decay = ema_decay
        self.activation_checkpointing, self._blocks_checkpointed = activation_checkpointing, False
        dit = set_fields(DiTOverrides, dit, "model.init_args.dit")
        self.config = DiTConfig.from_name(flavor, input_dim=self.spec.feature_dim, **dit)
        self.model = MotionDiT(self.config)
        self.diffusion = Diffusion(loss_weighting=loss_weighting)
        self.representation = get_representation(self.spec.representation, get_skeleton(self.spec.skeleton))
        defaults = self.value_group("sampling", sampling)  # kept in the hyper-parameters; read from these two
        self.stance_root = self.checked_stance_root(defaults.stance_root, "model.sampling.stance_root")
        self.smoothing = check_smoothing(defaults.smoothing, "model.sampling.smoothing")
        self.geometric_loss = GeometricLoss(self.representation, self.spec.fps)
        self.register_buffer("mean", torch.tensor(self.spec.mean, dtype=torch.float32), persistent=False)
        self.register_buffer("std", torch.tensor(self.spec.std, dtype=torch.float32), persistent=False)
        self._noise_gen: torch.Generator | None = None
        self._noise_state: Tensor | None = None  # restored from a checkpoint
        self._noise_seed: int | None = None  # a rank the checkpoint has no state for (elastic resume)
        self._window_start: float | None = None  # when the throughput's window opened
        self._window: tuple[int, Tensor] | None = None  # (samples, real frames) trained on in it
        self._window_logged: tuple[int, float] | None = None  # (global step, time) it was last logged

    def configure_model(self) -> None:
        """Activation checkpointing, applied to the blocks from outside the model code (once:
        Lightning configures the model again for every stage)."""
        if self.activation_checkpointing and not self._blocks_checkpointed:
            checkpoint_each(self.checkpointed_blocks())
            self._blocks_checkpointed = True

    def checkpointed_blocks(self) -> list[torch.nn.Module]:
        """The modules whose activations ``activation_checkpointing`` recomputes in backward."""
        return list(self.model.blocks)

    # -- features ------------------------------------------------------------------------
    def denormalize(self, x: Tensor) -> Tensor:
        return x * self.std.to(x.dtype) + self.mean.to(x.dtype)

    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    # -- training ------------------------------------------------------------------------
    def noise_generator(self) -> torch.Generator:
        """The RNG of timesteps and noise: its own, and saved in checkpoints, so that a resumed
        run draws exactly what the uninterrupted run would have drawn. Resumed on another number
        of ranks, rank r takes the saved state of rank r where there is one (the ranks both runs
        have keep their streams) and otherwise seeds from ``fresh_noise_seed(seed, step, r)``."""
        if self._noise_gen is None or self._noise_gen.device != self.device:
            self._noise_gen = torch.Generator(device=self.device)
            if self._noise_state is not None:
                self._noise_gen.set_state(self._noise_state)
            else:
                seed = self._noise_seed if self._noise_seed is not None else torch.initial_seed() + self.global_rank
                self._noise_gen.manual_seed(seed)
        return self._noise_gen

    def prepare(self, batch: dict) -> dict:
        """The batch as ``denoise`` needs it; the ControlNet stage adds its text condition here."""
        return batch

    def denoise(self, x_t: Tensor, t: Tensor, mask: Tensor | None, batch: dict) -> Tensor:
        """x̂0 for a noisy batch."""
        return self.model(x_t, t, mask)

    def denoise_noised(self, batch: dict, gen: torch.Generator) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Noise the prepared batch at random steps and denoise it: (x̂0, x0, t, prepared batch)."""
        batch = self.prepare(batch)
        x0, mask = batch["motion"], batch["mask"]  # (B, T, D), (B, T)
        t = self.diffusion.sample_timesteps(x0.shape[0], generator=gen, device=x0.device)
        noise = torch.randn(x0.shape, generator=gen, device=x0.device, dtype=x0.dtype) * mask[..., None]
        return self.denoise(self.diffusion.q_sample(x0, t, noise), t, mask, batch), x0, t, batch

    def diffusion_losses(self, batch: dict) -> dict[str, Tensor]:
        x0_hat, x0, t, batch = self.denoise_noised(batch, self.noise_generator())
        mask = batch["mask"]
        simple = self.diffusion.loss(x0_hat, x0, t, mask)
        vel, foot = self.geometric_loss(self.denormalize(x0_hat), self.denormalize(x0), mask, batch.get("offsets"))
        return {"loss": simple + self.loss.vel_weight * vel + self.loss.foot_weight * foot,
                "simple": simple, "vel": vel, "foot": foot}

    def training_losses(self, batch: dict) -> dict[str, Tensor]:
        return self.diffusion_losses(batch)

    def log_training(self, losses: dict[str, Tensor], batch: dict) -> None:
        super().log_training(losses, batch)
        self._count_throughput(batch)
        if self.logs_terms():
            self.log("train/lr", self.optimizers().param_groups[0]["lr"])
            self._log_throughput()

    def _count_throughput(self, batch: dict) -> None:
        """Add the batch to the throughput's window: its samples and real frames (a tensor on the batch's
        device, read only when logged: no device sync at every step)."""
        now = time.perf_counter()
        if self._window_logged is not None and self._window_logged[0] != self.global_step:
            # the step after a logged one: the window reopens where the logged step's last micro-batch closed it
            self._window_start, self._window, self._window_logged = self._window_logged[1], None, None
        if self._window_start is None:  # the run's first step: the window opens as it ends
            self._window_start = now
            return
        samples, frames = self._window or (0, 0)
        self._window = (samples + batch["motion"].shape[0], frames + batch["mask"].sum())

    def _log_throughput(self) -> None:
        """``train/samples_per_s`` and ``train/frames_per_s``, all ranks', over the window: the steps since the
        last logged ones (each micro-batch of an accumulated step logs the window so far; the logger keeps
        the last, which spans the whole step)."""
        now = time.perf_counter()
        if self._window is not None:
            (samples, frames), dt, world = self._window, now - self._window_start, self.trainer.world_size
            self.log("train/samples_per_s", world * samples / dt)
            self.log("train/frames_per_s", world * frames.item() / dt)
        self._window_logged = (self.global_step, now)

    def validation_step(self, batch: dict, batch_idx: int, stage: str = "val") -> None:
        gen = torch.Generator(device=self.device).manual_seed(batch_idx)  # the same noise every validation
        x0_hat, x0, t, batch = self.denoise_noised(batch, gen)
        loss = self.diffusion.loss(x0_hat, x0, t, batch["mask"])
        self.log(f"{stage}/simple", loss, batch_size=x0.shape[0], sync_dist=True)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        """``omg test``: the denoising loss on the test set; the generation metrics come from
        omg.callbacks.EvalCallback."""
        self.validation_step(batch, batch_idx, stage="test")

    def trainable_module(self) -> torch.nn.Module:
        return self.model

    def optimizer_groups(self) -> list[dict]:
        return [{"params": [p for p in self.trainable_module().parameters() if p.requires_grad]}]

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["noise_rng"] = self._gather_noise_states()

    def _gather_noise_states(self) -> Tensor:
        """Every rank's noise-RNG state, (world size, state bytes): each rank draws its own
        timesteps and noise, and a resumed run must give each rank its own back. Lightning calls
        ``on_save_checkpoint`` on every rank, so the gather is collective-safe."""
        state = self.noise_generator().get_state()  # (n,) uint8, on the CPU for every device
        trainer = self.attached_trainer()
        if trainer is None or trainer.world_size == 1:
            return state[None]
        return self.all_gather(state.to(self.device)).reshape(trainer.world_size, -1).cpu()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "noise_rng" in checkpoint:
            states = checkpoint["noise_rng"]
            states = states[None] if states.ndim == 1 else states  # one rank's, as older omg wrote
            trainer = self.attached_trainer()
            rank, world = (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)
            self._noise_gen, self._noise_state, self._noise_seed = None, None, None
            if rank < len(states):
                self._noise_state = states[rank].clone()  # set_state needs its own storage
            else:
                self._noise_seed = fresh_noise_seed(torch.initial_seed(), int(checkpoint.get("global_step", 0)), rank)
            if len(states) != world and rank == 0:
                kept = min(world, len(states))
                log.warning("resuming a %d-rank checkpoint on %d ranks: ranks below %d keep their noise RNG, %s; each "
                            "rank's data stream is the %d-rank run's from the saved position", len(states), world, kept,
                            "the others draw fresh ones from (seed, step, rank)" if world > kept
                            else f"those of ranks {kept} and up are dropped", world)
        super().on_load_checkpoint(checkpoint)

    # -- sampling ------------------------------------------------------------------------
    @torch.no_grad()
    def sample(self, texts: Sequence[str] | None, lengths: Tensor | Sequence[int],
               settings: SamplingSettings | None = None, *, progress: StepProgress | None = None) -> Tensor:
        """Samples, one per length: un-normalised features (B, max(lengths), D) with each motion
        generated at its own length (frames beyond it are padding, to be ignored); the ``Sampler``
        protocol (``omg.lit.sampling``).

        ``texts`` (B captions) condition a text-conditional module, guided with scale
        ``settings.guidance`` (default: the module's); None samples the unconditional motion prior.
        ``settings.sampler`` is a registered name (``omg.samplers``: ddim, dpmpp, euler) run for
        ``settings.steps`` steps. The EMA weights are used where kept (``use_ema``); ``seed`` fixes the
        initial noise, or ``seeds`` (one per motion) each motion's own: drawn at its own length from its own
        generator, so a motion does not depend on what it is sampled with. ``autocast`` (e.g.
        ``torch.bfloat16``) runs the network under autocast
        (matmuls and attention in that dtype, the sampler's update in the weights' dtype);
        ``compile`` runs it through ``torch.compile`` (compiled once per shape, then reused).
        ``stance_root`` (default: the module's) steps the root of every denoised estimate by its stance
        foot (``stance_denoiser``); ``control`` then steers it towards joint targets (``omg.lit.control``), on
        the frames of ``max(lengths)``. ``timeline`` (texts=None): each motion follows the timeline's texts by
        stretches of frames and body parts, their estimates blended at every step (``omg.lit.timeline``); with
        its separate chains, each text samples its own chain (K·B rows from the same x_T, stance_root and control
        applied to each chain), the chains joined at every step and in the motion returned. ``smoothing`` (default:
        the module's) smooths every estimate over time after the stance step and before the control's
        (``omg.lit.control.smoothed``), so that constraints are met on the smoothed motion.
        ``progress`` (a watcher of this call, not a setting) hears the solver's (step, steps) after each step.
        """
        settings = settings or SamplingSettings()
        if texts is not None and not self.text_conditional:
            raise UsageError(f"{type(self).__name__} is unconditional: sample it with texts=None")
        if settings.timeline is not None:
            check_timeline(settings.timeline, self.text_conditional, self.config.input_dim, type(self).__name__)
            if texts is not None:
                raise ValueError("a timeline carries its own texts: sample it with texts=None")
        mask = length_mask(lengths, device=self.device)  # (B, T) real frames
        if texts is not None and len(texts) != len(mask):
            raise ValueError(f"{len(texts)} texts for {len(mask)} lengths")
        self.check_sampling(settings, "stance_root")
        solver = SAMPLERS.get(settings.sampler)
        gen = torch.Generator(device=self.device).manual_seed(settings.seed)
        with modes_restored(self), self.ema_weights(settings.use_ema):
            self.eval()
            dtype = next(self.model.parameters()).dtype
            timeline, chains = settings.timeline, 1  # chains: K with separate chains (K·B rows), else 1
            shape = (*mask.shape, self.config.input_dim)
            given = {} if settings.seeds is None else {"noise": row_noise(settings.seeds, mask, shape[-1], dtype)}
            if timeline is None:  # a ControlNet trained with hints reads the control's targets (a timeline: steered)
                denoise = self.denoiser(texts, mask, settings.guidance, settings.control)
            elif timeline.separate:  # one chain per text, joined at every step (omg.lit.timeline)
                denoise = chains_denoiser(self.denoiser, timeline, mask, settings.guidance)
                chains = len(timeline.texts)
                if "noise" not in given:  # the chains start from the same x_T, drawn as one chain's would be
                    given["noise"] = torch.randn(shape, generator=gen, device=self.device, dtype=dtype)
                given["noise"] = given["noise"].repeat(chains, 1, 1)
                mask = mask.repeat(chains, 1)
                shape = (*mask.shape, shape[-1])
            else:  # each text's x̂0 blended at every step (omg.lit.timeline)
                denoise = timeline_denoiser(self.denoiser, timeline, mask, settings.guidance)
            if settings.autocast is not None:
                denoise = autocasting(denoise, self.device.type, settings.autocast)
            if settings.compile:
                denoise = torch.compile(denoise)
            strength = self.stance_root if settings.stance_root is None else settings.stance_root
            if strength:
                denoise = self.stance_denoiser(denoise, mask, strength)
            sigma = self.smoothing if settings.smoothing is None else settings.smoothing
            if sigma:  # after the stance step: a root stepped by alternating feet shakes too
                denoise = smoothed(denoise, sigma, mask, self.representation.contact_features())
            if settings.control is not None:  # with separate chains, every chain steered to the targets
                denoise = self.control_denoiser(denoise, mask, settings.control.tiled(chains), settings.steps)
            if progress is not None:  # passed only when watched: a plugin sampler need not take it
                given["progress"] = progress
            x = solver(self.diffusion, denoise, shape, steps=settings.steps, generator=gen, device=self.device,
                       dtype=dtype, mask=mask, **given)
            if chains > 1:
                x = compose_chains(x, timeline)
        return self.denormalize(x)

    def check_sampling(self, settings: SamplingSettings, key: str) -> None:
        """One line when ``settings`` step the root by the stance foot of a representation that cannot."""
        if settings.stance_root:
            self.checked_stance_root(settings.stance_root, key)

    def control_denoiser(self, denoise: Denoiser, mask: Tensor, control: Control, steps: int) -> Denoiser:
        """Spatial control: every x̂0 of a ``steps``-step sampler steered towards ``control``'s targets in global
        joint positions (``omg.lit.control.steered``), for ``control.frames`` = the longest motion's frames."""
        if control.frames != mask.shape[1] or control.targets.shape[0] not in (1, mask.shape[0]):
            raise ValueError(f"a control of {control.targets.shape[0]} x {control.frames} frames for "
                             f"{mask.shape[0]} motions of up to {mask.shape[1]} frames")
        dtype = next(self.model.parameters()).dtype
        return steered(denoise, control.to(self.device, dtype), self.representation, self.std.to(dtype),
                       self.mean.to(dtype), mask, self.diffusion.num_timesteps, steps)

    def denoiser(self, texts: Sequence[str] | None, mask: Tensor, guidance: float | None,
                 control: Control | None = None) -> Denoiser:
        """The (x_t, t) -> x̂0 function ``sample`` steps with, for these texts and frames (and ``control``, which a
        network that reads constraints reads; the prior steers alone, ``control_denoiser``)."""
        return lambda x, t: self.model(x, t, mask)

    def checked_stance_root(self, strength: float, key: str) -> float:
        """``strength`` if it is in [0, 1] and the representation can step its root by the stance foot."""
        strength = check_stance_root(strength, key)
        if strength and not self.representation.stance_root:
            self.representation.root_from_stance(torch.zeros(0))  # its one-line refusal
        return float(strength)

    def stance_denoiser(self, denoise: Denoiser, mask: Tensor, strength: float) -> Denoiser:
        """Contact-aware sampling: every x̂0 the network estimates gets its root stepped by its own stance
        foot (``Representation.root_from_stance``), so the sampler moves towards motion whose planted feet
        stay planted, and the last estimate, the sample, has them still."""
        def stepped(x: Tensor, t: Tensor) -> Tensor:
            x0 = denoise(x, t)  # (B, T, D) normalised
            moved = self.normalize(self.representation.root_from_stance(self.denormalize(x0), strength))
            return torch.where(mask[..., None], moved, x0)  # frames past a motion's length as they were
        return stepped


def row_noise(seeds: Sequence[int], mask: Tensor, dim: int, dtype: torch.dtype) -> Tensor:
    """x_T (B, T, dim) with row i drawn from its own generator seeded ``seeds[i]`` over its own frames (zero
    beyond): a row's noise depends only on its seed and length, not on the rows it is batched with."""
    noise = torch.zeros(*mask.shape, dim, device=mask.device, dtype=dtype)
    for i, (seed, frames) in enumerate(zip(seeds, mask.sum(dim=1).tolist())):
        gen = torch.Generator(device=mask.device).manual_seed(int(seed))
        noise[i, :frames] = torch.randn(frames, dim, generator=gen, device=mask.device, dtype=dtype)
    return noise


def autocasting(denoise: Denoiser, device_type: str, dtype: torch.dtype) -> Denoiser:
    """``denoise`` run under autocast to ``dtype``, its x̂0 returned in the sampler's dtype."""

    def mixed(x: Tensor, t: Tensor) -> Tensor:
        with torch.autocast(device_type, dtype=dtype):
            return denoise(x, t).to(x.dtype)

    return mixed


class PretrainModule(MotionDiffusionModule):
    """Unconditional x̂0-predicting MotionDiT.

    Args:
        flavor: DiT size preset: mini, base, large, huge or giant.
        dit: DiTConfig fields to override in the flavor's, e.g. ``{n_layers: 4}`` (``DiTOverrides``).
        optim: AdamW's lr, weight_decay, betas (OMG: 1e-4, 0) and warmup_steps, a linear LR warm-up, then
            cosine decay over the run's optimizer steps (``OptimSettings``).
        loss: vel_weight, foot_weight, the weights of L_vel and L_foot (OMG/MDM: 30 each;
            ``DiffusionLossWeights``).
        ema_decay: decay of the fp32 weight EMA kept in checkpoints (0 disables it).
        loss_weighting: λ_t, "uniform" or "min_snr" (see omg.diffusion).
        activation_checkpointing: recompute each block's activations in backward (less memory,
            about a third more compute); applied by ``configure_model``.
        sampling: the checkpoint's own sampling defaults, stance_root and smoothing (``SamplingDefaults``;
            omg's, not OMG's: 0, off), which a sampling call's settings override.
        spec: the data's representation, skeleton, fps and stats; linked from the data by ``omg fit``.
    """

    architecture_hparams = ("flavor", "dit", "spec")  # the rest may differ from the checkpoint's under --ckpt_path
    settings_groups = {"dit": DiTOverrides}

    def __init__(
        self,
        flavor: str = "base",
        dit: DiTOverrides | None = DiTOverrides(),  # every key listed by --print_config
        optim: OptimSettings = OptimSettings(lr=1e-4, weight_decay=0.0, warmup_steps=10_000),
        loss: DiffusionLossWeights = DiffusionLossWeights(),
        ema_decay: float = 0.9999,
        loss_weighting: str = "uniform",
        activation_checkpointing: bool = False,
        sampling: SamplingDefaults = SamplingDefaults(),
        spec: DataSpec | dict | None = None,
    ):
        super().__init__(flavor, dit, spec, optim=optim, loss=loss, ema_decay=ema_decay, loss_weighting=loss_weighting,
                         activation_checkpointing=activation_checkpointing, sampling=sampling)
        self.save_hyperparameters()
