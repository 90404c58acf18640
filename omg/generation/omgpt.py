"""OmniMotionGPT's generator: an animal motion per prompt, translated from a human motion (a file given, one
a second checkpoint makes from the prompt made about "a person", or the module's own human source)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from omg.errors import UsageError
from omg.generation.progress import Batch
from omg.generation.protocol import MAX_SECONDS, GeneratedMotion, GenerationCard, GenerationRequest, ModuleGenerator
from omg.generation.read import read_human_motion
from omg.generation.registry import register_generator
from omg.lit.human_source import generate_human, human_source_of
from omg.lit.omgpt import HUMAN_SKELETON, OmniMotionModule
from omg.lit.sampling import SamplingSettings
from omg.motion import get_representation
from omg.registry import SAMPLERS
from omg.text.omgpt import about_animal, choose_animal, to_person


@register_generator(OmniMotionModule)
class OmniMotionGenerator(ModuleGenerator):
    """Animal motions of an OmniMotionGPT checkpoint."""

    module: OmniMotionModule

    def generation_card(self) -> GenerationCard:
        m = self.module
        return GenerationCard(
            family="omgpt", skeleton=m.spec.skeleton, representation=m.spec.representation, fps=m.spec.fps,
            inputs=("text", "motion", "species"), needs=("text",), max_frames=round(MAX_SECONDS * m.spec.fps),
            samplers=tuple(SAMPLERS.names()), species=tuple(m.animal_names), source_generator=True,
            deterministic_source=True)

    def read_source(self, path: Path, joint_map: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A human motion file -> smpl22 maa features (T, 138) and offsets (22, 3) at the human data's rate:
        BVH / ASF-AMC / DeepMimic retargeted to smpl22, joints (T, 22, 3), or features (T, 138) maa or
        (T, 263) humanml3d263 in a ``.npy``."""
        return read_human_motion(Path(path), self.module.human_spec.fps, joint_map)

    def generate(self, request: GenerationRequest) -> list[GeneratedMotion]:
        """One animal motion per prompt and repeat, each from its own human motion: the source motion given
        (once per prompt: its translation is deterministic), one the ``source_module`` (an OMG ControlNet's
        generator) makes from the prompt made about "a person", or one from ``human_source``; seeds ``seed`` +
        index."""
        m = self.module
        names = m.animal_names
        if not names:
            raise UsageError("this OmniMotionGPT module knows no animal yet (train it first)")
        chosen = [choose_animal(p, names, request.species) for p in request.prompts]  # the sampler's rule
        frames, repeats = self._frames_and_repeats(request)
        if frames < 2:
            raise UsageError(f"the motion has {frames} frame(s) at {m.spec.fps:g} fps; need 2 or more")
        skeleton, maa = m.representation.skeleton, get_representation("maa", m.representation.skeleton)
        jobs = [(p, a, k) for p, a in zip(request.prompts, chosen) for k in range(repeats)]
        given = {"steps": request.steps, "sampler": request.sampler, "guidance": request.guidance}
        human_sampling = SamplingSettings(**{k: v for k, v in given.items() if v is not None})  # the second model's
        motions = []
        for index, (prompt, name, k) in enumerate(jobs):
            lengths = torch.tensor([frames])
            person = to_person(prompt, names)
            # one motion a batch; the steps are the second model's, sampling the human motion
            watch = Batch(request.progress, index, 1, len(jobs), human_sampling.steps if request.source is None and
                          request.source_module is not None else 0)
            if request.source is not None:
                human = torch.from_numpy(request.source[0][:frames])[None]
                human_offsets = torch.from_numpy(request.source[1])[None]
            elif request.source_module is not None:
                human, human_offsets = generate_human(request.source_module.module, [person], lengths, m.spec.fps,
                                                      replace(human_sampling, seed=request.seed + index),
                                                      progress=watch.solver)
            else:
                human, human_offsets = human_source_of(m).human_motion([person], lengths.to(m.device),
                                                                       SamplingSettings(seed=request.seed + index))
            # use_ema=False: the weights as loaded (load_module puts the EMA in)
            features = m.translate([prompt], human.to(m.device), human_offsets.to(m.device), lengths, [name],
                                   use_ema=False)[0].cpu().float()
            offsets = m.animal_offsets(name).cpu()
            rotations, root = maa.rotations_and_root(features)
            joints = skeleton.forward_kinematics(rotations, root, offsets).numpy().astype(np.float32)
            human_joints = m.human_rep.decode(human[0].float().cpu(), human_offsets[0].cpu()).numpy()
            motions.append(GeneratedMotion(
                features=features.numpy(), joints=joints, title=f"{prompt} ({name})",
                rotations=(rotations.numpy(), root.numpy(), offsets.numpy()),
                companions=[("{stem}.human", human_joints.astype(np.float32), HUMAN_SKELETON, None)],
                record={"prompt": prompt, "animal": name, "human_prompt": person, "repeat": k,
                        "animal_prompt": about_animal(prompt, name, names)}))
            watch.finish()
        return motions

    def _frames_and_repeats(self, request: GenerationRequest) -> tuple[int, int]:
        if request.source is None:
            return request.frames, request.num_samples
        return min(request.frames, len(request.source[0])), 1  # a given motion's translation is deterministic

    def generation_settings(self, request: GenerationRequest) -> dict[str, Any]:
        frames, repeats = self._frames_and_repeats(request)
        return {"animal": request.species, "human_source": "from_motion" if request.source is not None else
                "human_ckpt" if request.source_module is not None else self.module.human_source,
                "num_samples": repeats, "frames": frames, "steps": request.steps, "sampler": request.sampler,
                "guidance_scale": request.guidance}
