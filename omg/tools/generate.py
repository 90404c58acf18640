"""``omg generate``: sample motions from a checkpoint and write them with their settings.

Per sample it writes ``sample_NNN.features.npy`` (T, D) in the checkpoint's representation
(HumanML3D-compatible for humanml3d263), ``sample_NNN.joints.npy`` (T, J, 3) joint positions
in metres, Y up, and ``sample_NNN.bvh`` (rotations solved by IK on the model's skeleton);
``preview.gif`` shows the first motions side by side with their captions, and
``generation.json`` records every setting, so that a result can be reproduced exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import atomic_write, check_output_dir, npy_bytes, read_text, write_json
from omg.registry import SAMPLERS
from omg.retarget import read_rig
from omg.tools.args import FiniteFloat, PositiveInt, Seed, number_type, run
from omg.tools.common import removing_created
from omg.tools.export import OutputFormat

AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}
MAX_SECONDS = 60.0
MAX_PREVIEW = 6
Seconds = number_type("Seconds", float, [(">", 0.0), ("<=", MAX_SECONDS)],
                      f"a number of seconds in (0, {MAX_SECONDS:g}]")


def generate(
    prompts: list[str] | None = None,
    *,
    ckpt: Path,
    prompts_file: Path | None = None,
    unconditional: bool = False,
    num_samples: PositiveInt = 4,
    length: Seconds = 6.0,
    steps: PositiveInt = 200,
    sampler: str = "ddim",
    guidance: FiniteFloat | None = None,
    seed: Seed = 0,
    batch_size: PositiveInt = 32,
    ema: bool = True,
    preview: bool = True,
    preview_count: PositiveInt = MAX_PREVIEW,
    clean_contacts: bool = False,
    to_rig: Path | None = None,
    joint_map: str | None = None,
    format: OutputFormat = "bvh",
    device: str | None = None,
    autocast: Literal["bf16", "fp16"] | None = None,
    compile: bool = False,
    animal: str | None = None,
    from_motion: Path | None = None,
    human_ckpt: Path | None = None,
    out: Path = Path("out/generate"),
    command: str = "",
) -> dict:
    """Generate motions from a trained checkpoint.

    Writes per motion its features, joint positions and a BVH file, a preview.gif of the first
    motions and generation.json with every setting (the command reproduces the result).

    Args:
        prompts: text prompts (needs a text-conditioned checkpoint)
        ckpt: a .ckpt file, a DeepSpeed checkpoint directory or a .safetensors file
        prompts_file: a UTF-8 text file with one prompt per line
        unconditional: sample the pretrained motion prior without text
        num_samples: motions per prompt (or in total when unconditional)
        length: seconds per motion
        steps: sampling steps (at most the checkpoint's diffusion steps; OMG: 200 DDIM steps)
        sampler: a registered sampler: ddim (OMG's), dpmpp (DPM-Solver++(2M): ~20 steps), euler
        guidance: classifier-free guidance scale s (default: the checkpoint's, OMG: 4.5)
        seed: random seed
        batch_size: motions sampled at once
        ema: use the EMA of the weights (--no_ema: the trained weights)
        preview: write preview.gif
        preview_count: motions shown side by side in preview.gif
        clean_contacts: pin planted feet in the BVH files (removes foot skating)
        to_rig: write each motion onto this BVH file's rig (its hierarchy, names, channels, unit, rest pose)
        joint_map: the rig's joint map for --to_rig (a registered name or a YAML file; default: detected)
        format: bvh, or glb (glTF 2.0 binary: joint nodes, a skin and the animation)
        device: cpu, cuda, cuda:N or mps (default: cuda when available, else cpu)
        autocast: run the network under autocast in this dtype (bf16 on recent GPUs; the sampler's
            update stays in float32)
        compile: run the network through torch.compile (a one-off compilation, then faster steps)
        animal: OmniMotionGPT checkpoints: the animal (a species the checkpoint knows); it wins over the animal
            the prompt names, and the prompt is made about it (default: the one the prompt names)
        from_motion: OmniMotionGPT: the human motion to turn into the animal's (BVH, ASF/AMC or DeepMimic
            file retargeted to smpl22, a .joints.npy (T, 22, 3), or a features .npy in smpl22 maa or
            humanml3d263); one motion per prompt
        human_ckpt: OmniMotionGPT: an OMG ControlNet checkpoint that generates the human motion from the
            prompt made about "a person" (without either, the checkpoint's own human source)
        out: output folder (created; files in it are overwritten)
        command: the command line, recorded in generation.json

    Returns:
        The settings written to generation.json.
    """
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import MotionDiffusionModule, PretrainModule

    prompts = read_prompts(prompts or [], prompts_file)
    if unconditional == bool(prompts):
        raise UsageError("give prompts (or --prompts_file) for text-to-motion, or --unconditional to sample the "
                         "motion prior")
    SAMPLERS.get(sampler)  # an unknown name is one line before anything is loaded
    device = resolve_device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    out = check_output_dir(out)  # every input is checked before anything is written
    module = load_module(ckpt, default_class=PretrainModule, use_ema=ema)
    from omg.lit.omgpt import OmniMotionModule

    if joint_map is not None and to_rig is None:
        raise UsageError("--joint_map names the map of the --to_rig rig; give --to_rig RIG.bvh with it")

    if isinstance(module, OmniMotionModule):
        from omg.tools.animal import generate_animal

        return generate_animal(module, prompts, ckpt=ckpt, animal=animal, from_motion=from_motion,
                               human_ckpt=human_ckpt, num_samples=num_samples, length=length, steps=steps,
                               sampler=sampler, guidance=guidance, seed=seed, preview=preview,
                               preview_count=preview_count, device=device, out=out, command=command,
                               to_rig=to_rig, joint_map=joint_map, format=format)
    if animal is not None or from_motion is not None or human_ckpt is not None:
        raise UsageError(f"--animal, --from_motion and --human_ckpt need an OmniMotionGPT checkpoint; {ckpt} holds a "
                         f"{type(module).__name__}")
    if not isinstance(module, MotionDiffusionModule):
        from omg.lit.checkpoint import class_path

        raise UsageError(f"{ckpt} holds a {class_path(type(module))} checkpoint, not a "
                         f"{class_path(MotionDiffusionModule)}")
    if prompts and not module.text_conditional:
        raise UsageError(f"{ckpt} is an unconditional pretraining checkpoint: pass --unconditional, "
                         "or a text-conditioned (ControlNet) checkpoint for prompts")
    fps = module.spec.fps
    frames = round(length * fps)
    if frames < 2:
        raise UsageError(f"--length must be in (0, {MAX_SECONDS:g}] seconds and give at least 2 frames at {fps} fps, "
                         f"got {length}")
    if steps > module.diffusion.num_timesteps:
        raise UsageError(f"--steps must be in 1..{module.diffusion.num_timesteps} (the checkpoint's diffusion steps), "
                         f"got {steps}")
    rig = read_rig(to_rig, module.spec.skeleton, joint_map) if to_rig is not None else None  # checked before sampling
    module = module.to(device).eval()

    # one job per motion: (prompt or None, sample index); batched in order
    jobs = [(p, k) for p in (prompts or [None]) for k in range(num_samples)]
    settings = {
        "command": command,
        "ckpt": str(ckpt),
        "module": type(module).__name__,
        "unconditional": not prompts,
        "prompts": prompts,
        "num_samples": num_samples,
        "length_s": length,
        "frames": frames,
        "fps": fps,
        "steps": steps,
        "sampler": sampler,
        "autocast": autocast,
        "compile": compile,
        "guidance_scale": (guidance if guidance is not None else module.guidance_scale) if prompts
        else None,
        "seed": seed,
        "batch_size": batch_size,
        "ema": ema,
        "clean_contacts": clean_contacts,
        "to_rig": str(to_rig) if to_rig is not None else None,
        "joint_map": joint_map,
        "format": format,
        "representation": module.spec.representation,
        "skeleton": module.spec.skeleton,
    }
    existing = set(out.iterdir()) if out.is_dir() else set()
    try:
        with removing_created(out):
            out.mkdir(parents=True, exist_ok=True)
            settings["samples"], previews = _generate(module, prompts, jobs, frames, fps, out, steps=steps,
                                                      sampler=sampler, autocast=AUTOCAST.get(autocast), compile=compile,
                                                      guidance=guidance, seed=seed, batch_size=batch_size,
                                                      clean_contacts=clean_contacts, ckpt=ckpt,
                                                      rig=rig, joint_map=joint_map, format=format)
            write_json(out / "generation.json", settings)
            if preview:  # the first motions side by side with their captions
                from omg.io.render import render_gif

                shown = previews[:preview_count]
                motions, drawn = [m for m, _ in shown], module.representation.skeleton
                if rig is not None:  # the motions as written: on the rig's bones
                    from omg.retarget import onto_rig

                    motions = [onto_rig(m, drawn, rig, fps, joint_map).positions() for m in motions]
                    drawn = rig.skeleton()
                render_gif(out / "preview.gif", motions, drawn, fps, titles=[t for _, t in shown])
    except Exception:  # a failed run leaves no new files in a folder that existed before it
        if out.is_dir():
            for path in set(out.iterdir()) - existing:
                if path.is_file():
                    path.unlink(missing_ok=True)
        raise
    print(f"wrote {len(settings['samples'])} motions of {frames} frames ({length} s at {fps} fps) to {out}")
    return settings


def _control_character(text: str) -> str | None:
    return next((c for c in text if (ord(c) < 32 and c != "\t") or ord(c) == 127 or 0xDC80 <= ord(c) <= 0xDCFF), None)


def read_prompts(prompts: list[str], prompts_file: str | Path | None = None) -> list[str]:
    """The prompts given and those of ``prompts_file`` (one per line), checked."""
    prompts = list(prompts)
    for i, prompt in enumerate(prompts):
        if (c := _control_character(prompt)) is not None:
            raise UsageError(f"prompt {i + 1} holds the control character or undecodable byte {c!r}; give plain text")
    if prompts_file:
        lines = read_text(prompts_file, "--prompts_file").splitlines()
        for number, line in enumerate(lines, start=1):
            if (c := _control_character(line)) is not None:
                raise UsageError(f"--prompts_file {prompts_file}: line {number} holds the control character {c!r}; "
                                 "expected a text file with one prompt per line")
        prompts += [line.strip() for line in lines if line.strip()]
    if empty := [i for i, p in enumerate(prompts) if not p.strip()]:
        raise UsageError(f"prompt {empty[0] + 1} is empty; give a sentence such as \"a person walks forward\"")
    return prompts


def resolve_device(name: str) -> torch.device:
    """``--device`` as a torch device that exists on this machine."""
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda", "mps"):
        raise UsageError(f"--device {name!r}: not a device; use cpu, cuda, cuda:N or mps")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise UsageError(f"--device {name}: no CUDA GPU is available here; use --device cpu")
        if device.index is not None and device.index >= count:
            raise UsageError(f"--device {name}: this machine has {count} CUDA GPU{'s' if count > 1 else ''} "
                             f"(cuda:0{f' to cuda:{count - 1}' if count > 1 else ''})")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise UsageError(f"--device {name}: MPS (Apple GPU) is not available here; use --device cpu")
    return device


def _generate(module, prompts: list[str], jobs: list, frames: int, fps: float, out: Path, *, steps: int,
              sampler: str, autocast: torch.dtype | None, compile: bool, guidance: float | None, seed: int,
              batch_size: int,
              clean_contacts: bool, ckpt: Path, rig=None, joint_map: str | None = None,
              format: str = "bvh") -> tuple[list[dict], list[tuple[np.ndarray, str]]]:
    """Sample the jobs batch by batch and write each motion's files; the records of the motions, and
    the motions with their captions for the preview."""
    from omg.export import export_motion

    records, previews = [], []
    for start in range(0, len(jobs), batch_size):
        batch = jobs[start : start + batch_size]
        batch_seed = seed + start
        texts = [p for p, _ in batch] if prompts else None  # None: the unconditional motion prior
        # (n, T, D); use_ema=False: load_module has already put the EMA weights in
        features = module.sample(texts, [frames] * len(batch), steps=steps, sampler=sampler, guidance=guidance,
                                 seed=batch_seed, use_ema=False, autocast=autocast, compile=compile)
        if not torch.isfinite(features).all():
            scale = f" or --guidance {guidance:g} too large" if prompts and guidance is not None else ""
            raise UsageError(f"the model produced NaN or inf motions: a diverged checkpoint ({ckpt}){scale}")
        joints = module.representation.decode(features.float())  # (n, T, J, 3)
        for i, (prompt, k) in enumerate(batch):
            name = f"sample_{len(records):03d}"
            atomic_write(out / f"{name}.features.npy", npy_bytes(features[i].float().cpu().numpy()))
            positions = joints[i].cpu().numpy().astype(np.float32)
            atomic_write(out / f"{name}.joints.npy", npy_bytes(positions))
            export_motion(out / name, positions, module.representation.skeleton, fps, preview=False,  # BVH / glb
                          clean_contacts=clean_contacts, rig=rig, joint_map=joint_map, format=format)
            records.append({"file": name, "prompt": prompt, "repeat": k, "batch_seed": batch_seed})
            previews.append((positions, prompt or "unconditional"))
    return records, previews


def main(argv: list[str]) -> None:
    run(generate, argv, "omg generate", positional="prompts")
