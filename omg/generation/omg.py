"""OMG's generator: text-to-motion (ControlNet) or the unconditional prior (pretraining), sampled by the
diffusion module's ``sample``."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from omg.errors import UsageError
from omg.generation.control import KINDS, contact_sources, unmet
from omg.generation.progress import Batch
from omg.generation.protocol import (
    MAX_SECONDS,
    GeneratedMotion,
    GenerationCard,
    GenerationRequest,
    ModuleGenerator,
    NumberRange,
)
from omg.generation.registry import register_generator
from omg.lit.control import constraint_errors
from omg.lit.pretrain import MotionDiffusionModule
from omg.lit.sampling import MAX_SMOOTHING, MAX_STANCE_ROOT, SamplingSettings
from omg.registry import SAMPLERS


@register_generator(MotionDiffusionModule)
class OmgGenerator(ModuleGenerator):
    """Motions of an OMG diffusion checkpoint (a ControlNet, or the pretrained prior)."""

    module: MotionDiffusionModule

    def generation_card(self) -> GenerationCard:
        m = self.module
        return GenerationCard(
            family="omg", skeleton=m.spec.skeleton, representation=m.spec.representation, fps=m.spec.fps,
            inputs=("text", "unconditional") if m.text_conditional else ("unconditional",),  # D_u: the prior
            max_frames=round(MAX_SECONDS * m.spec.fps), samplers=tuple(SAMPLERS.names()),
            max_steps=m.diffusion.num_timesteps, default_steps=min(200, m.diffusion.num_timesteps),
            guidance=getattr(m, "guidance_scale", None), row_seeds=True, timeline=timeline_kinds(m), constraints=KINDS,
            contacts=contact_sources(m.representation),
            options={**({"stance_root": f"step the root by the stance foot while sampling, 0..{MAX_STANCE_ROOT:g} "
                                        "(removes foot sliding)"} if m.representation.stance_root else {}),
                     "smoothing": f"smooth every denoised estimate over time, a Gaussian of this many frames, "
                                  f"0..{MAX_SMOOTHING:g} (removes frame-to-frame shake)"},
            option_ranges={**({"stance_root": NumberRange(0.0, MAX_STANCE_ROOT, default=m.stance_root)}
                              if m.representation.stance_root else {}),
                           "smoothing": NumberRange(0.0, MAX_SMOOTHING, default=m.smoothing)})  # frames; 0: off

    def read_source(self, path, joint_map: str | None = None):
        raise UsageError("an OMG checkpoint generates from prompts (or nothing), not from a source motion")

    def generate(self, request: GenerationRequest) -> list[GeneratedMotion]:
        """``num_samples`` motions per prompt (in total when unconditional), sampled ``batch_size`` at a time,
        each batch with seed ``seed`` + its first motion's index; the weights as loaded (``load_module`` puts
        the EMA in)."""
        m = self.module
        prompts, steps = request.prompts or [None], request.steps or self.generation_card().default_steps
        jobs = [(p, k) for p in prompts for k in range(request.num_samples)]
        timeline = None if request.timeline is None else request.timeline.resolve(request.frames, m.spec.fps,
                                                                                  m.representation)
        # use_ema=False: the weights as loaded (load_module puts the EMA in)
        sampling = SamplingSettings(steps=steps, sampler=request.sampler or "ddim", guidance=request.guidance,
                                    use_ema=False, autocast=request.autocast, compile=request.compile,
                                    stance_root=request.options.get("stance_root"), timeline=timeline,
                                    smoothing=request.options.get("smoothing"),
                                    control=request.control)
        untitled = "unconditional" if timeline is None else "timeline: " + " | ".join(timeline.texts)
        if request.row_seeds is not None and len(request.row_seeds) != len(jobs):
            raise ValueError(f"{len(request.row_seeds)} row seeds for {len(jobs)} motions")
        motions = []
        for start in range(0, len(jobs), request.batch_size):
            batch = jobs[start : start + request.batch_size]
            batch_seed = request.seed + start
            seeds = None if request.row_seeds is None else request.row_seeds[start : start + len(batch)]
            texts = [p for p, _ in batch] if request.prompts else None  # None: the unconditional motion prior
            watch = Batch(request.progress, start, len(batch), len(jobs), steps)
            features = m.sample(texts, [request.frames] * len(batch), replace(sampling, seed=batch_seed, seeds=seeds),
                                progress=watch.solver)  # (n, T, D)
            joints = m.representation.decode(features.float())  # (n, T, J, 3)
            reached = None if request.control is None else constraint_errors(joints, request.control.to(joints.device))
            for i, (prompt, k) in enumerate(batch):
                record = {"prompt": prompt, "repeat": k,
                          **({"batch_seed": batch_seed} if seeds is None else {"seed": seeds[i]})}
                if reached is not None:  # each constraint's worst distance, and those beyond their tolerance
                    record["control_error_m"] = {name: round(e, 4) for name, e in reached[i].items()}
                    record["control_unmet"] = {n: round(e, 4) for n, e in unmet(reached[i], request.control).items()}
                motions.append(GeneratedMotion(
                    features=features[i].float().cpu().numpy(), joints=joints[i].cpu().numpy().astype(np.float32),
                    title=prompt or untitled, record=record))
            watch.finish()
        return motions

    def generation_settings(self, request: GenerationRequest) -> dict[str, Any]:
        m = self.module
        texts = bool(request.prompts) or request.timeline is not None
        return {"unconditional": not texts, "steps": request.steps or self.generation_card().default_steps,
                "sampler": request.sampler or "ddim",
                "guidance_scale": (request.guidance if request.guidance is not None else m.guidance_scale)
                if texts else None, "batch_size": request.batch_size,
                "stance_root": request.options.get("stance_root", m.stance_root),
                **({"smoothing": smoothing} if (smoothing := request.options.get("smoothing", m.smoothing)) else {}),
                **({} if request.timeline is None else {"timeline": request.timeline.to_dict()})}


def timeline_kinds(module: MotionDiffusionModule) -> tuple[str, ...]:
    """What a timeline may hold for ``module``: segments for a text-conditioned one, body parts too where its
    representation maps each feature to a joint (``Representation.channel_joints``); none for the prior."""
    if not module.text_conditional:
        return ()
    try:
        module.representation.channel_joints()
    except UsageError:
        return ("timeline",)
    return ("timeline", "parts")
