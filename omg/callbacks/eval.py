"""``EvalCallback``: text-to-motion metrics while training, and the published protocol at test."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch import Tensor, nn

from omg.callbacks.run import log_scalars, run_dir, sampling, stop_if_signalled
from omg.errors import UsageError
from omg.evaluation import (
    EvalSettings,
    PromptSet,
    build_evaluator,
    check_evaluator_spec,
    evaluate,
    file_prompt_set,
    markdown_table,
    parse_metrics,
    prompt_set,
    protocol,
    write_report,
)
from omg.lit.sampling import Sampler, SamplingSettings, sampler_of
from omg.metrics.following import load_prompts
from omg.registry import METRICS


def check_eval_data(data: L.LightningDataModule | None, key: str) -> None:
    if data is None or not getattr(data, "val_urls", None):
        raise UsageError(f"{key} draws its prompts from the validation/test set: set data.val to a shard directory")


def eval_samples(trainer: L.Trainer, key: str) -> tuple[list[dict], Any]:
    """The decoded clips of the data module's validation/test set and its window sampler."""
    check_eval_data(trainer.datamodule, key)
    return trainer.datamodule.val_clips().samples, trainer.datamodule


def check_generative(module: L.LightningModule, key: str, sampling: SamplingSettings) -> Sampler:
    """``module`` as the ``Sampler`` the callback ``key`` calls, able to sample with ``sampling``; one line
    otherwise."""
    sampler = sampler_of(module, key)
    if sampling.stance_root is not None:
        sampler.check_sampling(sampling, f"{key}.stance_root")
    return sampler


def sampling_settings(key: str, steps: int, guidance: float | None, use_ema: bool, sampler: str,
                      stance_root: float | None, smoothing: float | None) -> SamplingSettings:
    """How a callback samples, checked when the callback is made (an unknown sampler fails here, not after
    training)."""
    return SamplingSettings(steps=steps, guidance=guidance, use_ema=use_ema, sampler=sampler, stance_root=stance_root,
                            smoothing=smoothing, key=key)


def conditioning(module: Sampler, texts: list[str]) -> list[str] | None:
    """What ``sample`` gets as texts: the captions for a text-conditional model, None otherwise."""
    return list(texts) if module.text_conditional else None


class EvalCallback(Callback):
    """Generation metrics from a frozen text–motion evaluator.

    Every ``every_n_steps`` optimizer steps one pass over a fixed seeded prompt set is logged as
    ``eval/<metric>``; at ``omg test`` the protocol runs ``replications`` passes with different
    prompt sets and sampling seeds and logs, prints and writes (``eval.json``, ``eval.md`` in the
    run directory) each metric's mean ± 95% confidence interval.

    Args:
        evaluator: an evaluator checkpoint path, or ``{t2m: {checkpoint, glove_dir, mean_std_dir}}``
            for the T2M (HumanML3D) evaluator port.
        metrics: registered metric names, each optionally with options: ``[fid, {r_precision:
            {pool_size: 32}}, ...]``; default fid, r_precision, mm_dist, diversity, multimodality.
        num_prompts: prompts per pass (drawn from data.val, repeating clips with new captions
            and windows when the set is smaller).
        every_n_steps: evaluate during fit every this many steps (0: only at test).
        replications: passes of the test protocol (T2M/MDM: 20).
        mm_prompts, mm_repeats: MultiModality generates each of the first mm_prompts prompts
            mm_repeats times (T2M: 100 × 30).
        steps, guidance, use_ema, sampler, stance_root, smoothing: sampling settings passed to the model's
            ``sample`` (sampler: a registered name, ``omg.samplers``: ddim, dpmpp, euler)
            (guidance, stance_root, smoothing None: the model's own).
        batch_size: prompts generated at once on each rank.
        seed: seeds the prompt sets and the sampling; a run is deterministic for a seed.
        reference: also report the set-wise metrics of the real motions as ``real/<metric>``.
        prompts: a prompt file with targets (``omg.metrics.following``: ``following`` for the
            built-in set, or a YAML path) in place of captions drawn from data.val: each of its
            prompts is generated ``samples_per_prompt`` times per pass and scored by what the
            motion does (metrics: following, and others that need no real motion: diversity,
            multimodality, foot_skating; the evaluator may then be left out).
        samples_per_prompt: generations of each prompt of a prompt file per pass.
        name: the report's file name and the logged keys' prefix (default ``eval``: ``eval.json``,
            ``eval/<metric>``; ``OODEvalCallback``: ``eval_ood.json``), so that two evaluations of
            one run (e.g. two feature scales) keep apart.
    """

    report_name = "eval"

    def __init__(
        self,
        evaluator: str | dict[str, Any] | nn.Module | None = None,
        metrics: list[str | dict[str, Any]] | None = None,
        num_prompts: int = 1000,
        every_n_steps: int = 0,
        replications: int = 20,
        mm_prompts: int = 100,
        mm_repeats: int = 30,
        steps: int = 200,
        guidance: float | None = None,
        use_ema: bool = True,
        sampler: str = "ddim",
        stance_root: float | None = None,
        smoothing: float | None = None,
        batch_size: int = 64,
        seed: int = 0,
        reference: bool = True,
        prompts: str | None = None,
        samples_per_prompt: int = 4,
        name: str | None = None,
    ):
        key = "EvalCallback"
        for option, value, low in (("num_prompts", num_prompts, 1), ("every_n_steps", every_n_steps, 0),
                                   ("replications", replications, 1), ("mm_prompts", mm_prompts, 1),
                                   ("mm_repeats", mm_repeats, 2), ("steps", steps, 1), ("batch_size", batch_size, 1),
                                   ("samples_per_prompt", samples_per_prompt, 1)):
            if not isinstance(value, int) or value < low:
                raise UsageError(f"{key}.{option} must be an integer >= {low}, got {value!r}")
        if isinstance(evaluator, str) and not Path(evaluator).exists():
            raise UsageError(f"{key}.evaluator: no evaluator checkpoint at {evaluator}")
        self.evaluator_spec = evaluator
        self.metrics = parse_metrics(metrics, key=f"{key}.metrics")
        self.prompt_file = None
        if prompts is not None:
            self.prompt_file = load_prompts(None if prompts == "following" else prompts)
            self.samples_per_prompt = samples_per_prompt
            self.num_prompts = len(self.prompt_file) * samples_per_prompt
            if wrong := [n for n in self.metrics if getattr(METRICS.get(n), "needs_real", True)]:
                raise UsageError(f"{key}.metrics: {', '.join(wrong)} compare with real motions, which a prompt file "
                                 "(EvalCallback.prompts) does not have; use following, diversity, multimodality "
                                 "or foot_skating")
        if evaluator is None and (wrong := [n for n in self.metrics if getattr(METRICS.get(n), "needs_embeddings",
                                                                              True)]):
            raise UsageError(f"{key}.evaluator: {', '.join(wrong)} read the evaluator's embeddings; set an evaluator "
                             "checkpoint")
        self.every_n_steps, self.replications = every_n_steps, replications
        if self.prompt_file is None:
            self.num_prompts = num_prompts
        self.sampling = sampling_settings(key, steps, guidance, use_ema, sampler, stance_root, smoothing)
        self.settings = EvalSettings(batch_size=batch_size, mm_prompts=mm_prompts, mm_repeats=mm_repeats,
                                     reference=reference)
        self.seed = seed
        self.log_prefix = name or "eval"
        if name:
            self.report_name = name
        self.evaluator: nn.Module | None = None
        self._samples: list[dict] | None = None
        self._fixed: PromptSet | None = None
        self._last_step = -1

    def preflight(self, model: L.LightningModule, data: L.LightningDataModule | None) -> None:
        """The checks that need no trainer: ``omg.tools.lightning`` runs them before the run creates its
        folder, ``setup`` again for a Trainer used without the CLI."""
        check_generative(model, "EvalCallback", self.sampling)
        if self.prompt_file is None:
            check_eval_data(data, "EvalCallback")
        elif data is None:
            raise UsageError("EvalCallback.prompts: the data module is needed for the features' representation and fps")
        if self.evaluator is None and self.evaluator_spec is not None:
            self.evaluator = build_evaluator(self.evaluator_spec, key="EvalCallback.evaluator")
        if self.evaluator is not None:
            check_evaluator_spec(self.evaluator, data.spec, key="EvalCallback.evaluator")
        # generated and real motions are compared at one frame rate: the model's must be the data's
        check_evaluator_spec(model, data.spec, key=f"the model ({type(model).__name__})")
        for name, options in self.metrics.items():  # pool sizes and pair counts the prompt set can fill
            for option, default in (("pool_size", 32 if name == "r_precision" else None),
                                    ("num_pairs", 300 if name == "diversity" else None)):
                need = options.get(option, default)
                if need is not None and self.num_prompts < need:
                    raise UsageError(f"EvalCallback.num_prompts={self.num_prompts} is below {name}'s {option}={need}: "
                                     f"raise num_prompts or set metrics: [{{{name}: {{{option}: N}}}}]")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        self.preflight(pl_module, trainer.datamodule)
        if self.prompt_file is None:
            self._samples, _ = eval_samples(trainer, "EvalCallback")
        self.spec, self._windows = trainer.datamodule.spec, trainer.datamodule.windows

    def prompts(self, replication: int) -> PromptSet:
        """The prompt set of a replication (replication 0 is the fixed set used during fit); a
        prompt file's is the same in every replication, whose sampling seeds differ."""
        if self.prompt_file is not None:
            return file_prompt_set(self.prompt_file, self.samples_per_prompt, self.spec.fps, self._windows.max_len)
        return prompt_set(self._samples, self.num_prompts, self.seed + replication, self._windows)

    def run_once(self, trainer: L.Trainer, module: L.LightningModule, replication: int) -> dict[str, float]:
        """One pass: {metric key: value}, identical on every rank."""
        prompts = self._fixed if replication == 0 and self._fixed is not None else self.prompts(replication)
        if replication == 0:
            self._fixed = prompts

        def generate(texts: list[str], lengths: Tensor, seed: int) -> Tensor:
            stop_if_signalled(trainer)  # before each batch: a SIGTERM ends the protocol within one
            return self.generate(module, texts, lengths, seed)

        with sampling(module), trainer.precision_plugin.forward_context():
            return evaluate(generate, self.evaluator, prompts, self.metrics, seed=self.seed, replication=replication,
                            settings=self.settings, spec=self.spec, device=module.device,
                            rank=trainer.global_rank, world_size=trainer.world_size)

    def generate(self, module: L.LightningModule, texts: list[str], lengths: Tensor, seed: int) -> Tensor:
        """The model's motions for a batch of prompts (``OODEvalCallback`` also counts what they started from)."""
        sampler = sampler_of(module, "EvalCallback")
        return sampler.sample(conditioning(sampler, texts), lengths, replace(self.sampling, seed=seed))

    # -- fit -------------------------------------------------------------------------------
    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, *args) -> None:
        step = trainer.global_step
        if self.every_n_steps and step % self.every_n_steps == 0 and step != self._last_step:
            self._last_step = step  # several batches share a step under gradient accumulation
            values = self.run_once(trainer, pl_module, 0)
            log_scalars(trainer, {f"{self.log_prefix}/{k}": v for k, v in values.items()})

    # -- test: the protocol -----------------------------------------------------------------
    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        def replication(r: int) -> dict[str, float]:
            start = time.perf_counter()
            values = self.run_once(trainer, pl_module, r)
            rank_zero_info(f"omg: evaluation replication {r + 1}/{self.replications}: {self.num_prompts} prompts "
                           f"in {time.perf_counter() - start:.0f} s")
            return values

        rank_zero_info(f"omg: evaluating {self.replications} replications of {self.num_prompts} prompts "
                       f"({self.sampling.steps} sampling steps)")
        summary = protocol(replication, self.replications)
        for key, s in summary.items():
            pl_module.log(f"{self.log_prefix}/{key}", s["mean"])
            pl_module.log(f"{self.log_prefix}/{key}_ci95", s["ci95"])
        directory = run_dir(trainer)
        settings = {"checkpoint": str(trainer.ckpt_path) if trainer.ckpt_path else None,
                    "model": type(pl_module).__name__, "evaluator": self._describe_evaluator(),
                    "replications": self.replications, "num_prompts": self.num_prompts, "seed": self.seed,
                    "mm_prompts": self.settings.mm_prompts, "mm_repeats": self.settings.mm_repeats,
                    **({"prompts": len(self.prompt_file), "samples_per_prompt": self.samples_per_prompt}
                       if self.prompt_file is not None else {}),
                    **{f"sampling_{k}": v for k, v in self.sampling.report().items()}, "metrics": self.metrics}
        self._report(directory, summary, settings)

    @rank_zero_only
    def _report(self, directory: Path, summary: dict, settings: dict) -> None:
        json_path, md_path = write_report(directory, summary, settings, name=self.report_name)
        print(f"\n{markdown_table(summary, self.replications)}\n\nwritten to {json_path} and {md_path}")

    def _describe_evaluator(self) -> str:
        spec = self.evaluator_spec
        return spec if isinstance(spec, str) or spec is None else type(self.evaluator).__name__
