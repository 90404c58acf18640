"""``omg generate``: sample motions from a checkpoint and write them with their settings.

Per sample it writes ``sample_NNN.features.npy`` (T, D) in the checkpoint's representation
(HumanML3D-compatible for humanml3d263), ``sample_NNN.joints.npy`` (T, J, 3) joint positions
in metres, Y up, and ``sample_NNN.bvh`` (rotations solved by IK on the model's skeleton);
``preview.gif`` shows the first motions side by side with their captions, and
``generation.json`` records every setting, so that a result can be reproduced exactly.
"""

from __future__ import annotations

import unicodedata
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import atomic_write, check_output_dir, npy_bytes, read_text, write_json
from omg.lit.generative import (
    MAX_SECONDS,
    GeneratedMotion,
    GenerationCard,
    GenerationRequest,
    GenerativeModule,
    check_request,
)
from omg.registry import SAMPLERS
from omg.retarget import read_rig
from omg.tools.args import ClosedUnitInterval, FiniteFloat, PositiveInt, Seed, number_type, run
from omg.tools.common import removing_created
from omg.tools.export import OutputFormat

AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}
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
    steps: PositiveInt | None = None,
    sampler: str | None = None,
    guidance: FiniteFloat | None = None,
    seed: Seed = 0,
    batch_size: PositiveInt = 32,
    ema: bool = True,
    preview: bool = True,
    preview_count: PositiveInt = MAX_PREVIEW,
    clean_contacts: bool = False,
    stance_root: ClosedUnitInterval | None = None,
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
    """Generate motions from a trained checkpoint of any family.

    Writes per motion its features, joint positions and a BVH file, a preview.gif of the first
    motions and generation.json with every setting (the command reproduces the result). What a
    checkpoint generates from (prompts, nothing, a source motion, a species) is its generation
    card's (``omg.lit.generative``); an option it does not take is one line before sampling.

    Args:
        prompts: text prompts (needs a text-conditioned checkpoint)
        ckpt: a .ckpt file, a DeepSpeed checkpoint directory or a .safetensors file
        prompts_file: a UTF-8 text file with one prompt per line
        unconditional: sample the pretrained motion prior without text
        num_samples: motions per prompt (or in total when unconditional)
        length: seconds per motion
        steps: sampling steps (at most the checkpoint's diffusion steps; default OMG's 200 DDIM steps)
        sampler: a registered sampler: ddim (OMG's, the default), dpmpp (DPM-Solver++(2M): ~20 steps), euler
        guidance: classifier-free guidance scale s (default: the checkpoint's, OMG: 4.5)
        seed: random seed
        batch_size: motions sampled at once
        ema: use the EMA of the weights (--no_ema: the trained weights)
        preview: write preview.gif
        preview_count: motions shown side by side in preview.gif
        clean_contacts: pin planted feet in the BVH files (removes foot skating)
        stance_root: OMG checkpoints of humanml3d263 motion: step the root by the stance foot at every
            sampling step, this much in [0, 1] (default: the checkpoint's; removes foot sliding while sampling)
        to_rig: write each motion onto this BVH file's rig (its hierarchy, names, channels, unit, rest pose)
        joint_map: the rig's joint map for --to_rig (a registered name or a YAML file; default: detected)
        format: bvh, or glb (glTF 2.0 binary: joint nodes, a skin and the animation)
        device: cpu, cuda, cuda:N or mps (default: cuda when available, else cpu)
        autocast: run the network under autocast in this dtype (bf16 on recent GPUs; the sampler's
            update stays in float32)
        compile: run the network through torch.compile (a one-off compilation, then faster steps)
        animal: checkpoints that take a species (OmniMotionGPT, habit transfer): the animal; it wins over the
            animal the prompt names, and the prompt is made about it (default: the one the prompt names)
        from_motion: checkpoints that take a source motion: the motion file (OmniMotionGPT: the human motion to
            turn into the animal's, a BVH, ASF/AMC or DeepMimic file retargeted to smpl22, a .joints.npy
            (T, 22, 3), or a features .npy in smpl22 maa or humanml3d263; one motion per prompt)
        human_ckpt: checkpoints whose source motion a second model may make (OmniMotionGPT): a text-to-motion
            checkpoint (OMG ControlNet) that generates the human motion from the prompt made about "a person"
            (without either, the checkpoint's own human source)
        out: output folder (created; files in it are overwritten)
        command: the command line, recorded in generation.json

    Returns:
        The settings written to generation.json.
    """
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import PretrainModule

    prompts = read_prompts(prompts or [], prompts_file)
    if animal is not None:  # a description of an animal goes to the text encoder as a prompt does
        check_plain_text(animal, "--animal")
    if unconditional == bool(prompts) and from_motion is None:
        raise UsageError("give prompts (or --prompts_file) for text-to-motion, or --unconditional to sample the "
                         "motion prior")
    if sampler is not None:
        SAMPLERS.get(sampler)  # an unknown name is one line before anything is loaded
    if joint_map is not None and to_rig is None:
        raise UsageError("--joint_map names the map of the --to_rig rig; give --to_rig RIG.bvh with it")
    if from_motion is not None and human_ckpt is not None:
        raise UsageError("give --from_motion (a human motion file) or --human_ckpt (a ControlNet checkpoint), not both")
    device = resolve_device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    # every input is checked before anything is written; a folder where a motion file goes would fail the write
    out = check_output_dir(out, files=output_files("sample_*", format, "generation.json", preview))
    module = generative_module(ckpt, load_module(ckpt, default_class=PretrainModule, use_ema=ema))
    card = module.generation_card()
    request = GenerationRequest(prompts=prompts or None, frames=round(length * card.fps), num_samples=num_samples,
                                seed=seed, steps=steps, sampler=sampler, guidance=guidance, species=animal,
                                batch_size=batch_size, autocast=AUTOCAST.get(autocast), compile=compile,
                                options={} if stance_root is None else {"stance_root": stance_root})
    if human_ckpt is not None:
        request.source_module = generative_module(human_ckpt, load_module(human_ckpt)).to(device).eval()
    request.source = from_motion  # read once the card says the model takes it
    check_request(card, request, f"{ckpt} ({type(module).__name__})")
    if from_motion is not None:
        request.source = module.read_source(from_motion)
    rig = read_rig(to_rig, card.skeleton, joint_map) if to_rig is not None else None  # checked before sampling
    module = module.to(device).eval()
    motions = module.generate(request)
    check_finite_motions(motions, ckpt, f" or --guidance {guidance:g} too large" if prompts and guidance is not None
                         else "")
    settings = {"command": command, "ckpt": str(ckpt), "module": type(module).__name__, "family": card.family,
                "prompts": prompts, "num_samples": num_samples, "length_s": length, "frames": request.frames,
                "fps": card.fps, "seed": seed, "ema": ema, "autocast": autocast, "compile": compile,
                "from_motion": None if from_motion is None else str(from_motion),
                "human_ckpt": None if human_ckpt is None else str(human_ckpt), "clean_contacts": clean_contacts,
                "to_rig": None if to_rig is None else str(to_rig), "joint_map": joint_map, "format": format,
                **module.generation_settings(request),
                "representation": card.representation, "skeleton": card.skeleton}
    write_generation(out, motions, card, settings, rig=rig, joint_map=joint_map, format=format,
                     clean_contacts=clean_contacts, preview=preview, preview_count=preview_count)
    frames = settings["frames"]
    print(f"wrote {len(motions)} motions of {frames} frames ({frames / card.fps:g} s at {card.fps:g} fps) to {out}")
    return settings


def output_files(names: str, format: str, settings_file: str, preview: bool) -> tuple[str, ...]:
    """Glob patterns of the files ``write_generation`` writes for motions named like ``names``."""
    return (f"{names}.*.npy", f"{names}.{format}", settings_file, *(("preview.gif",) if preview else ()))


def generative_module(ckpt: Path, module) -> GenerativeModule:
    """``module`` when it implements the generation interface, else one line naming what ``ckpt`` holds."""
    if not isinstance(module, GenerativeModule):
        from omg.lit.checkpoint import class_path

        raise UsageError(f"{ckpt} holds a {class_path(type(module))} checkpoint, which generates no motion")
    return module


def check_finite_motions(motions: list[GeneratedMotion], ckpt: Path, hint: str = "") -> None:
    """One line when a model produced NaN or inf motions (a diverged checkpoint), before anything is written."""
    if not all(np.isfinite(m.features).all() and np.isfinite(m.joints).all() for m in motions):
        raise UsageError(f"the model produced NaN or inf motions: a diverged checkpoint ({ckpt}){hint}")


def write_generation(out: Path, motions: list[GeneratedMotion], card: GenerationCard, settings: dict, *,
                     names: list[str] | None = None, settings_file: str = "generation.json", rig=None,
                     joint_map: str | None = None, format: str = "bvh", clean_contacts: bool = False,
                     preview: bool = True, preview_count: int = MAX_PREVIEW) -> dict:
    """Write the motions of one generation and its settings: the one writer of every family and command.

    Per motion (``names``, default ``sample_NNN``): ``.features.npy`` (T, D), ``.joints.npy`` (T, J, 3), and
    ``.bvh`` (or ``.glb``): the model's rotations as they are when it makes them, else rotations solved by
    IK; on ``rig`` when given, with planted feet pinned under ``clean_contacts`` (both from the joints).
    Companion motions (a human source, a transfer's source) as ``.joints.npy``; ``preview.gif`` with the
    first ``preview_count`` motions (companions with a title beside theirs); ``settings_file`` with each
    motion's record under ``samples``. A failure leaves no new file: a folder it created is removed, one
    that existed keeps exactly the files it had."""
    from omg.export import export_motion, model_motion
    from omg.io.bvh import write_bvh
    from omg.io.gltf import write_glb
    from omg.skeleton import get_skeleton

    skeleton, fps = get_skeleton(card.skeleton), card.fps
    existing = set(out.iterdir()) if out.is_dir() else set()
    try:
        with removing_created(out):
            out.mkdir(parents=True, exist_ok=True)
            records, shown = [], []
            for i, motion in enumerate(motions):
                name = names[i] if names else f"sample_{i:03d}"
                atomic_write(out / f"{name}.features.npy", npy_bytes(np.asarray(motion.features, np.float32)))
                atomic_write(out / f"{name}.joints.npy", npy_bytes(np.asarray(motion.joints, np.float32)))
                for stem, joints, _, title in motion.companions:
                    companion = np.asarray(joints, np.float32)
                    atomic_write(out / f"{stem.format(stem=name)}.joints.npy", npy_bytes(companion))
                    if title is not None and i < preview_count:
                        shown.append((joints, title))
                if motion.rotations is not None and rig is None and not clean_contacts:  # as the model made them
                    rotations, root, offsets = motion.rotations
                    if format == "bvh":
                        write_bvh(out / f"{name}.bvh", skeleton, rotations, root, fps, offsets)
                    else:
                        write_glb(out / f"{name}.glb", model_motion(skeleton, rotations, root, offsets, fps, name))
                else:
                    export_motion(out / name, motion.joints, skeleton, fps, preview=False,
                                  clean_contacts=clean_contacts, rig=rig, joint_map=joint_map, format=format)
                records.append({"file": name, **motion.record})
                if i < preview_count:
                    shown.append((motion.joints, motion.title))
            settings["samples"] = records
            write_json(out / settings_file, settings)
            if preview:  # the first motions side by side with their captions
                from omg.io.render import render_gif

                drawn, drawn_skeleton = [m for m, _ in shown], skeleton
                if rig is not None:  # the motions as written: on the rig's bones
                    from omg.retarget import onto_rig

                    drawn = [onto_rig(m, skeleton, rig, fps, joint_map).positions() for m in drawn]
                    drawn_skeleton = rig.skeleton()
                render_gif(out / "preview.gif", drawn, drawn_skeleton, fps, titles=[t for _, t in shown])
    except Exception:  # a failed run leaves no new files in a folder that existed before it
        if out.is_dir():
            for path in set(out.iterdir()) - existing:
                if path.is_file():
                    path.unlink(missing_ok=True)
        raise
    return settings


def _control_character(text: str) -> str | None:
    """The first character of ``text`` no text encoder should see: a control character but tab (C0, DEL, C1), or a
    surrogate, which UTF-8 cannot encode (an undecodable byte of the command line, or JSON's lone ``\\ud800``)."""
    return next((c for c in text if c != "\t" and unicodedata.category(c) in ("Cc", "Cs")), None)


def check_plain_text(text: str, what: str) -> str:
    """``text`` when it is plain text (``_control_character``); one line naming ``what`` otherwise. The one check of
    text given to a model, for ``omg generate`` and ``omg serve`` alike."""
    if (c := _control_character(text)) is not None:
        kind = "the control character" if unicodedata.category(c) == "Cc" else "a lone surrogate or undecodable byte"
        raise UsageError(f"{what} holds {kind} {c!r}, which is not text; give plain text")
    return text


def read_prompts(prompts: list[str], prompts_file: str | Path | None = None) -> list[str]:
    """The prompts given and those of ``prompts_file`` (one per line), checked."""
    prompts = list(prompts)
    for i, prompt in enumerate(prompts):
        check_plain_text(prompt, f"prompt {i + 1}")
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


def main(argv: list[str]) -> None:
    run(generate, argv, "omg generate", positional="prompts")
