"""OMG stage 1: unconditional MotionDiT pretraining on unlabeled motion.

Loss (MDM-style geometric terms on positions decoded from the representation):
    L = L_simple + vel_weight · L_vel + foot_weight · L_foot
where L_simple is the λ_t-weighted x̂0 MSE in normalised feature space, L_vel compares joint
velocities of x̂0 and x0, and L_foot penalises the velocity of feet that are in contact in x0.
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import nullcontext
from typing import Any, Callable

import lightning as L
import torch
from torch import Tensor

from omg.diffusion import Diffusion
from omg.data.windows import length_mask
from omg.errors import UsageError
from omg.lit.ema import EMA
from omg.models.dit import DiTConfig, MotionDiT
from omg.motion import Representation, get_representation
from omg.motion.humanml3d263 import FOOT_CONTACT_SPEED
from omg.skeleton import get_skeleton

log = logging.getLogger(__name__)
SPEC_KEYS = ("representation", "skeleton", "fps", "feature_dim", "mean", "std")


def check_spec(spec: dict | None) -> dict:
    if spec is None:
        raise UsageError("the model needs its data spec (representation, stats): `omg fit` links it from the data; "
                         "in Python pass spec=MotionDataModule(...).spec")
    if missing := [k for k in SPEC_KEYS if k not in spec]:
        raise UsageError(f"model spec lacks {', '.join(missing)}")
    return spec


def contact_from_positions(positions: Tensor, feet: tuple[int, ...], fps: float) -> Tensor:
    """(B, T, J, 3) -> (B, T-1, F) 1 where a foot moves slower than HumanML3D's contact speed
    (0.002 m² per 20-fps frame, ≈ 0.89 m/s), the same speed at any fps."""
    step = positions[:, 1:, list(feet)] - positions[:, :-1, list(feet)]  # (B, T-1, F, 3)
    speed = step.norm(dim=-1) * fps
    return (speed < FOOT_CONTACT_SPEED).float()


class GeometricLoss:
    """Velocity and foot-contact losses on decoded joint positions (shared by stage 1 and 2)."""

    def __init__(self, representation: Representation, fps: float):
        self.rep, self.fps = representation, fps

    def __call__(self, x0_hat: Tensor, x0: Tensor, mask: Tensor, offsets: Tensor | None) -> tuple[Tensor, Tensor]:
        """x0_hat, x0: (B, T, D) un-normalised features; mask (B, T). Returns (L_vel, L_foot)."""
        with torch.autocast(x0.device.type, enabled=False):
            pos_hat = self.rep.decode(x0_hat.float(), offsets)  # (B, T, J, 3)
            pos = self.rep.decode(x0.float(), offsets)
            vel_hat = pos_hat[:, 1:] - pos_hat[:, :-1]  # (B, T-1, J, 3)
            vel = pos[:, 1:] - pos[:, :-1]
            pair = (mask[:, 1:] & mask[:, :-1]).float()  # (B, T-1) both frames real
            frames = pair.sum().clamp(min=1)
            l_vel = ((vel_hat - vel).pow(2).mean(dim=(-1, -2)) * pair).sum() / frames

            feet = self.rep.skeleton.feet
            contact = self.rep.foot_contacts(x0.float())  # (B, T, F) or None
            contact = (contact[:, :-1] > 0.5).float() if contact is not None else contact_from_positions(pos, feet, self.fps)
            foot_vel = vel_hat[:, :, list(feet)]  # (B, T-1, F, 3)
            l_foot = ((foot_vel.pow(2).sum(-1) * contact).mean(-1) * pair).sum() / frames
        return l_vel, l_foot


def warmup_cosine(warmup_steps: int, total_steps: int):
    """LR multiplier: linear warm-up to 1, then cosine decay to 0 at ``total_steps``."""

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / warmup_steps
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return factor


class MotionDiffusionModule(L.LightningModule):
    """What the diffusion stages share: the x̂0-predicting MotionDiT, its losses, optimizer and
    schedule, the weight EMA and sampling. Subclasses save their own hyper-parameters."""

    text_conditional = False  # whether sample_for_eval follows its texts
    clip_sampling = "windows"  # what data.clips=auto cuts from clips (omg.data.windows)

    def __init__(self, flavor: str, dit: dict[str, Any] | None, lr: float, weight_decay: float, warmup_steps: int,
                 loss_weighting: str, spec: dict | None):
        super().__init__()
        if lr <= 0 or weight_decay < 0 or warmup_steps < 0:
            raise UsageError(f"model.lr must be > 0 and model.weight_decay, model.warmup_steps >= 0; got {lr}, {weight_decay}, {warmup_steps}")
        self.spec = check_spec(spec)
        fields = set(DiTConfig.__dataclass_fields__) - {"name", "input_dim"}
        if unknown := set(dit or {}) - fields:
            raise UsageError(f"unknown model.dit field(s) {sorted(unknown)}; DiTConfig fields: {', '.join(sorted(fields))}")
        self.config = DiTConfig.from_name(flavor, input_dim=spec["feature_dim"], **(dit or {}))
        self.model = MotionDiT(self.config)
        self.diffusion = Diffusion(loss_weighting=loss_weighting)
        self.representation = get_representation(spec["representation"], get_skeleton(spec["skeleton"]))
        self.geometric_loss = GeometricLoss(self.representation, spec["fps"])
        self.register_buffer("mean", torch.tensor(spec["mean"], dtype=torch.float32), persistent=False)
        self.register_buffer("std", torch.tensor(spec["std"], dtype=torch.float32), persistent=False)
        self.ema: EMA | None = None
        self._noise_gen: torch.Generator | None = None
        self._noise_state: Tensor | None = None  # restored from a checkpoint
        self._last_batch_time: float | None = None

    # -- features ------------------------------------------------------------------------
    def denormalize(self, x: Tensor) -> Tensor:
        return x * self.std.to(x.dtype) + self.mean.to(x.dtype)

    def normalize(self, x: Tensor) -> Tensor:
        return (x - self.mean.to(x.dtype)) / self.std.to(x.dtype)

    # -- training ------------------------------------------------------------------------
    def noise_generator(self) -> torch.Generator:
        """The RNG of timesteps and noise: its own, and saved in checkpoints, so that a resumed
        run draws exactly what the uninterrupted run would have drawn."""
        if self._noise_gen is None or self._noise_gen.device != self.device:
            self._noise_gen = torch.Generator(device=self.device)
            if self._noise_state is not None:
                self._noise_gen.set_state(self._noise_state)
            else:
                self._noise_gen.manual_seed(torch.initial_seed() + self.global_rank)
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
        h = self.hparams
        return {"loss": simple + h.vel_weight * vel + h.foot_weight * foot, "simple": simple, "vel": vel, "foot": foot}

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        losses = self.diffusion_losses(batch)
        if not torch.isfinite(losses["loss"]):
            raise FloatingPointError(
                f"non-finite loss at step {self.global_step} ({ {k: float(v) for k, v in losses.items()} }); "
                "lower model.lr, enable gradient clipping, or check the data with `omg shards inspect`"
            )
        self.log_dict({f"train/{k}": v for k, v in losses.items()}, prog_bar=True, batch_size=batch["motion"].shape[0])
        self.log("train/lr", self.optimizers().param_groups[0]["lr"])
        self._log_throughput(batch)
        return losses["loss"]

    def _log_throughput(self, batch: dict) -> None:
        now = time.perf_counter()
        if self._last_batch_time is not None:
            dt, world = now - self._last_batch_time, self.trainer.world_size
            self.log("train/samples_per_s", world * batch["motion"].shape[0] / dt)
            self.log("train/frames_per_s", world * batch["mask"].sum().item() / dt)
        self._last_batch_time = now

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

    def configure_optimizers(self):
        h = self.hparams
        params = [p for p in self.trainable_module().parameters() if p.requires_grad]
        optimizer = torch.optim.AdamW(params, lr=h.lr, weight_decay=h.weight_decay, betas=tuple(h.betas))
        total = int(self.trainer.estimated_stepping_batches)
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, warmup_cosine(h.warmup_steps, total))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # -- EMA -----------------------------------------------------------------------------
    def on_fit_start(self) -> None:
        if self.hparams.ema_decay > 0 and self.ema is None:
            self.ema = EMA(self.trainable_module(), self.hparams.ema_decay)

    def optimizer_step(self, *args, **kwargs) -> None:
        super().optimizer_step(*args, **kwargs)
        # Once per real optimizer step, and before checkpoint callbacks see the step. Strategies
        # that accumulate gradients themselves (DeepSpeed) get this call on every micro-batch and
        # step on the last one of each window: the EMA must not average over micro-batches, or
        # its horizon would depend on the accumulation and so on the number of GPUs.
        if self.ema is not None and not self.trainer.fit_loop._should_accumulate():
            self.ema.update(self.trainable_module())

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # which class to rebuild, also for checkpoints written outside LightningCLI
        checkpoint["module_class"] = f"{type(self).__module__}.{type(self).__qualname__}"
        if self.ema is not None:
            checkpoint["ema"] = self.ema.state_dict()
        checkpoint["noise_rng"] = self._gather_noise_states()

    def _gather_noise_states(self) -> Tensor:
        """Every rank's noise-RNG state, (world size, state bytes): each rank draws its own
        timesteps and noise, and a resumed run must give each rank its own back. Lightning calls
        ``on_save_checkpoint`` on every rank, so the gather is collective-safe."""
        state = self.noise_generator().get_state()  # (n,) uint8, on the CPU for every device
        trainer = self._trainer
        if trainer is None or trainer.world_size == 1:
            return state[None]
        return self.all_gather(state.to(self.device)).reshape(trainer.world_size, -1).cpu()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        if "noise_rng" in checkpoint:
            states = checkpoint["noise_rng"]
            states = states[None] if states.ndim == 1 else states  # one rank's, as older omg wrote
            rank = self.global_rank if self._trainer is not None else 0
            if rank < len(states):
                self._noise_gen, self._noise_state = None, states[rank].clone()  # set_state needs its own storage
            else:
                log.warning("this checkpoint holds the noise RNG of %d ranks; rank %d starts a fresh one, so "
                            "the run does not repeat the uninterrupted one exactly", len(states), rank)
        if "ema" in checkpoint and self.hparams.ema_decay > 0:
            self.ema = EMA(self.trainable_module(), self.hparams.ema_decay)
            self.ema.load_state_dict(checkpoint["ema"])

    # -- sampling ------------------------------------------------------------------------
    @torch.no_grad()
    def ddim(self, denoise: Callable[[torch.dtype], Callable], num: int, frames: int, steps: int, seed: int,
             use_ema: bool, mask: Tensor | None = None) -> Tensor:
        """DDIM samples, un-normalised features (num, frames, D), with the EMA weights swapped in
        when asked; ``denoise(dtype)`` makes the (x_t, t) -> x̂0 callable for the weights' dtype
        (closing over ``mask`` (num, frames), which keeps padded frames at zero, when given)."""
        gen = torch.Generator(device=self.device).manual_seed(seed)
        trained = self.trainable_module()
        with self.ema.swapped_in(trained) if (use_ema and self.ema is not None) else nullcontext():
            trained.eval()
            dtype = next(self.model.parameters()).dtype
            x = self.diffusion.ddim_sample(denoise(dtype), (num, frames, self.config.input_dim), steps=steps,
                                           generator=gen, device=self.device, dtype=dtype, mask=mask)
        return self.denormalize(x)

    def sample(self, num: int, frames: int, steps: int = 200, seed: int = 0, use_ema: bool = True) -> Tensor:
        """Unconditional DDIM samples of the DiT, un-normalised features (num, frames, D)."""
        self.model.eval()
        return self.ddim(lambda dtype: self.model, num, frames, steps, seed, use_ema)

    def sample_for_eval(self, texts: list[str], lengths: Tensor, seed: int, steps: int = 200,
                        guidance: float | None = None, use_ema: bool = True) -> Tensor:
        """The evaluation hook (omg.callbacks.EvalCallback): one motion per text with its own length,
        (B, max(lengths), D) un-normalised, padding ignored. Stage 1 is unconditional, so the texts
        and ``guidance`` are ignored; each sample is generated at its length (masked), not cropped."""
        self.model.eval()
        mask = length_mask(lengths, device=self.device)
        return self.ddim(lambda dtype: lambda x, t: self.model(x, t, mask), len(texts), mask.shape[1], steps, seed,
                         use_ema, mask)


class PretrainModule(MotionDiffusionModule):
    """Unconditional x̂0-predicting MotionDiT.

    Args:
        flavor: DiT size preset: mini, base, large, huge or giant.
        dit: DiTConfig fields to override, e.g. ``{n_layers: 4, activation_checkpointing: true}``.
        lr, weight_decay, betas: AdamW settings (OMG: 1e-4, 0).
        warmup_steps: linear LR warm-up, then cosine decay over the run's optimizer steps.
        vel_weight, foot_weight: weights of L_vel and L_foot (OMG/MDM: 30 each).
        ema_decay: decay of the fp32 weight EMA kept in checkpoints (0 disables it).
        loss_weighting: λ_t, "uniform" or "min_snr" (see omg.diffusion).
        spec: the data's representation, skeleton, fps and stats; linked from the data by ``omg fit``.
    """

    def __init__(
        self,
        flavor: str = "base",
        dit: dict[str, Any] | None = None,
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        betas: tuple[float, float] = (0.9, 0.999),
        warmup_steps: int = 10_000,
        vel_weight: float = 30.0,
        foot_weight: float = 30.0,
        ema_decay: float = 0.9999,
        loss_weighting: str = "uniform",
        spec: dict | None = None,
    ):
        super().__init__(flavor, dit, lr, weight_decay, warmup_steps, loss_weighting, spec)
        self.save_hyperparameters()
