"""``RenderCallback``: stick-figure previews of fixed prompts while training, into the run
directory and to whichever logger is configured."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.loggers import TensorBoardLogger, WandbLogger

from omg.callbacks.eval import check_generative, conditioning, sampling_settings
from omg.callbacks.run import run_dir, sampling
from omg.errors import UsageError
from omg.io.render import render_gif
from omg.lit.sampling import sampler_of


class RenderCallback(Callback):
    """Every ``every_n_steps`` steps, one GIF per prompt with ``num_samples`` samples side by side
    (``renders/step_<N>/prompt_<i>.gif`` in the run directory), also logged as wandb videos or
    TensorBoard videos (frames as an image without moviepy). Rank 0 renders; the samples are
    seeded, so every preview of a run shows the same noise.

    Args:
        prompts: captions to render; None takes ``num_prompts`` captions of data.val. A model
            that samples unconditionally ignores them and renders ``num_prompts`` rows.
        num_prompts: prompts taken from data.val when ``prompts`` is None.
        num_samples: samples per prompt, side by side.
        seconds: length of each sample.
        every_n_steps: render every this many optimizer steps; also once at the end of fit.
        steps, guidance, use_ema, sampler, stance_root, smoothing: sampling settings passed to the model's
            ``sample`` (sampler: a registered name, ``omg.samplers``: ddim, dpmpp, euler; guidance, stance_root,
            smoothing None: the model's own).
        seed: the sampling seed.
        max_frames, dpi: GIF size (frames are subsampled to at most max_frames).
    """

    def __init__(
        self,
        prompts: list[str] | None = None,
        num_prompts: int = 2,
        num_samples: int = 3,
        seconds: float = 4.0,
        every_n_steps: int = 1000,
        steps: int = 50,
        guidance: float | None = None,
        use_ema: bool = True,
        sampler: str = "ddim",
        stance_root: float | None = None,
        smoothing: float | None = None,
        seed: int = 0,
        max_frames: int = 60,
        dpi: int = 60,
    ):
        if every_n_steps < 1 or num_samples < 1 or num_prompts < 1 or seconds <= 0 or steps < 1:
            raise UsageError("RenderCallback.every_n_steps, num_samples, num_prompts, steps must be >= 1 "
                             f"and seconds > 0; got {every_n_steps}, {num_samples}, {num_prompts}, {steps}, {seconds}")
        if prompts is not None and (not prompts or not all(isinstance(p, str) and p.strip() for p in prompts)):
            raise UsageError(f"RenderCallback.prompts must be a non-empty list of non-empty captions, got {prompts!r}")
        self.prompts, self.num_prompts, self.num_samples, self.seconds = prompts, num_prompts, num_samples, seconds
        self.every_n_steps, self.seed = every_n_steps, seed
        self.sampling = sampling_settings("RenderCallback", steps, guidance, use_ema, sampler, stance_root, smoothing)
        self.max_frames, self.dpi = max_frames, dpi
        self._last_step = -1

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        sampler = check_generative(pl_module, "RenderCallback", self.sampling)
        self.spec = trainer.datamodule.spec if trainer.datamodule is not None else pl_module.spec
        if not sampler.text_conditional:
            self._texts = [""] * self.num_prompts
        elif self.prompts is not None:
            self._texts = list(self.prompts)
        else:
            from omg.callbacks.eval import eval_samples

            captions = [s["texts"][0] for s in eval_samples(trainer, "RenderCallback (prompts: null)")[0] if s["texts"]]
            if not captions:
                raise UsageError("RenderCallback: data.val has no captions; set RenderCallback.prompts")
            self._texts = captions[: self.num_prompts]

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args) -> None:
        if trainer.global_step % self.every_n_steps == 0:
            self.render(trainer, pl_module)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.render(trainer, pl_module)

    def render(self, trainer: L.Trainer, pl_module: L.LightningModule) -> list[Path]:
        """Render the previews of the current step (once per step); returns the GIF paths."""
        step = trainer.global_step
        directory = run_dir(trainer) / "renders" / f"step_{step:07d}"  # every rank: it broadcasts
        if step == self._last_step or not trainer.is_global_zero:
            return []
        self._last_step = step
        frames = max(2, round(self.seconds * self.spec.fps))
        texts = [t for t in self._texts for _ in range(self.num_samples)]
        sampler = sampler_of(pl_module, "RenderCallback")
        with sampling(pl_module):
            features = sampler.sample(conditioning(sampler, texts), torch.full((len(texts),), frames),
                                      replace(self.sampling, seed=self.seed))
            joints = pl_module.representation.decode(features.float()).cpu().numpy()  # (P·S, T, J, 3)
        directory.mkdir(parents=True, exist_ok=True)
        paths = []
        for i, text in enumerate(self._texts):
            panels = joints[i * self.num_samples:(i + 1) * self.num_samples]
            titles = [f"{text} ({k + 1})" if text else f"sample {i * self.num_samples + k + 1}"
                      for k in range(self.num_samples)]
            paths.append(render_gif(directory / f"prompt_{i:02d}.gif", list(panels), self.spec.skeleton,
                                    self.spec.fps, titles=titles, max_frames=self.max_frames, dpi=self.dpi))
        for logger in trainer.loggers:
            log_gifs(logger, paths, self._texts, step, self.spec.fps)
        return paths


def log_gifs(logger, paths: list[Path], captions: list[str], step: int, fps: float) -> None:
    """wandb: videos; TensorBoard: videos (needs moviepy) or the middle frame as an image; other
    loggers (CSV) keep the files in the run directory only."""
    if isinstance(logger, WandbLogger):
        logger.log_video("render", [str(p) for p in paths], step=step, caption=[c or "unconditional" for c in captions],
                         format=["gif"] * len(paths))
    elif isinstance(logger, TensorBoardLogger):
        from importlib.util import find_spec

        from PIL import Image, ImageSequence

        for i, path in enumerate(paths):
            frames = np.stack([np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(path))])
            video = torch.from_numpy(frames).permute(0, 3, 1, 2)[None]  # (1, T, C, H, W) uint8
            if find_spec("moviepy"):  # add_video encodes with moviepy (and only prints when it is missing)
                logger.experiment.add_video(f"render/prompt_{i:02d}", video, step, fps=max(1, round(fps)))
            else:
                logger.experiment.add_image(f"render/prompt_{i:02d}", video[0, len(frames) // 2], step)
