"""``omg generate``: sample motions from a checkpoint and write them with their settings.

Per sample it writes ``sample_NNN.features.npy`` (T, D) in the checkpoint's representation
(HumanML3D-compatible for humanml3d263), ``sample_NNN.joints.npy`` (T, J, 3) joint positions
in metres, Y up, and ``sample_NNN.bvh`` (rotations solved by IK on the model's skeleton);
``preview.gif`` shows the first motions side by side with their captions, and
``generation.json`` records every setting, so that a result can be reproduced exactly.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np
import torch

from omg.cli import (ToolParser, check_output_dir, finite_float, positive_float, positive_int, read_text,
                     removing_created, seed_int)
from omg.data.shards import atomic_write, npy_bytes, write_json
from omg.errors import UsageError

MAX_SECONDS = 60.0
MAX_PREVIEW = 6


def parse_args(argv: list[str]):
    p = ToolParser(prog="omg generate", description="Generate motions from a trained checkpoint.")
    p.add_argument("prompts", nargs="*", help="text prompts (needs a text-conditioned checkpoint)")
    p.add_argument("--prompts-file", help="a text file with one prompt per line")
    p.add_argument("--ckpt", required=True, help="a .ckpt file, a DeepSpeed checkpoint directory or a .safetensors file")
    p.add_argument("--unconditional", action="store_true", help="sample the pretrained motion prior without text")
    p.add_argument("--num-samples", type=positive_int, default=4, help="motions per prompt (or in total when unconditional)")
    p.add_argument("--length", type=positive_float, default=6.0, help=f"seconds per motion, at most {MAX_SECONDS:g}")
    p.add_argument("--steps", type=positive_int, default=200, help="DDIM steps")
    p.add_argument("--guidance", type=finite_float, help="classifier-free guidance scale s (default: the checkpoint's, OMG: 4.5)")
    p.add_argument("--seed", type=seed_int, default=0, help="random seed, an integer in [0, 2^63)")
    p.add_argument("--batch-size", type=positive_int, default=32)
    p.add_argument("--no-ema", action="store_true", help="use the trained weights instead of their EMA")
    p.add_argument("--no-preview", action="store_true", help="skip the GIF preview")
    p.add_argument("--preview-count", type=positive_int, default=MAX_PREVIEW,
                   help=f"motions shown side by side in preview.gif (default {MAX_PREVIEW})")
    p.add_argument("--clean-contacts", action="store_true", help="pin planted feet in the BVH files (removes foot skating)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="cpu, cuda, cuda:N or mps")
    p.add_argument("--out", default="out/generate", help="output folder (created; files in it are overwritten)")
    return p.parse_args(argv)


def _control_character(text: str) -> str | None:
    return next((c for c in text if (ord(c) < 32 and c != "\t") or ord(c) == 127 or 0xDC80 <= ord(c) <= 0xDCFF), None)


def read_prompts(args) -> list[str]:
    prompts = list(args.prompts)
    for i, prompt in enumerate(prompts):
        if (c := _control_character(prompt)) is not None:
            raise UsageError(f"prompt {i + 1} holds the control character or undecodable byte {c!r}; give plain text")
    if args.prompts_file:
        path = args.prompts_file
        lines = read_text(path, "--prompts-file").splitlines()
        for number, line in enumerate(lines, start=1):
            if (c := _control_character(line)) is not None:
                raise UsageError(f"--prompts-file {path}: line {number} holds the control character {c!r}; "
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
    from omg.lit.checkpoint import load_module
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import MotionDiffusionModule, PretrainModule

    args = parse_args(argv)
    prompts = read_prompts(args)
    if args.unconditional == bool(prompts):
        raise UsageError("give prompts (or --prompts-file) for text-to-motion, or --unconditional to sample the motion prior")
    if args.length > MAX_SECONDS:
        raise UsageError(f"--length must be in (0, {MAX_SECONDS}] seconds, got {args.length}")
    device = resolve_device(args.device)
    out = check_output_dir(args.out)  # every input is checked before anything is written
    module = load_module(args.ckpt, default_class=PretrainModule, use_ema=not args.no_ema, expect=MotionDiffusionModule)
    if prompts and not isinstance(module, ControlNetModule):
        raise UsageError(f"{args.ckpt} is an unconditional pretraining checkpoint: pass --unconditional, "
                         "or a text-conditioned (ControlNet) checkpoint for prompts")
    fps = module.spec["fps"]
    frames = round(args.length * fps)
    if frames < 2:
        raise UsageError(f"--length must be in (0, {MAX_SECONDS}] seconds and give at least 2 frames at {fps} fps, "
                         f"got {args.length}")
    if args.steps > module.diffusion.num_timesteps:
        raise UsageError(f"--steps must be in 1..{module.diffusion.num_timesteps} (the checkpoint's diffusion steps), "
                         f"got {args.steps}")
    module = module.to(device).eval()

    # one job per motion: (prompt or None, sample index); batched in order
    jobs = [(p, k) for p in (prompts or [None]) for k in range(args.num_samples)]
    existing = set(out.iterdir()) if out.is_dir() else set()
    try:
        with removing_created(out):
            out.mkdir(parents=True, exist_ok=True)
            settings = _generate(module, args, argv, prompts, jobs, frames, fps, out)
    except Exception:  # a failed run leaves no new files in a folder that existed before it
        if out.is_dir():
            for path in set(out.iterdir()) - existing:
                if path.is_file():
                    path.unlink(missing_ok=True)
        raise
    print(f"wrote {len(settings['samples'])} motions of {frames} frames ({args.length} s at {fps} fps) to {out}")


def _generate(module, args, argv: list[str], prompts: list[str], jobs: list, frames: int, fps: float, out: Path) -> dict:
    from omg.io.export import export_motion
    from omg.io.render import render_gif

    records, previews = [], []
    for start in range(0, len(jobs), args.batch_size):
        batch = jobs[start : start + args.batch_size]
        seed = args.seed + start
        if prompts:
            features = module.generate([p for p, _ in batch], frames, steps=args.steps, seed=seed, scale=args.guidance,
                                       use_ema=False)
        else:
            features = module.sample(len(batch), frames, steps=args.steps, seed=seed, use_ema=False)  # (n, T, D)
        if not torch.isfinite(features).all():
            scale = f" or --guidance {args.guidance:g} too large" if prompts and args.guidance is not None else ""
            raise UsageError(f"the model produced NaN or inf motions: a diverged checkpoint ({args.ckpt}){scale}")
        joints = module.representation.decode(features.float())  # (n, T, J, 3)
        for i, (prompt, k) in enumerate(batch):
            name = f"sample_{len(records):03d}"
            atomic_write(out / f"{name}.features.npy", npy_bytes(features[i].float().cpu().numpy()))
            positions = joints[i].cpu().numpy().astype(np.float32)
            atomic_write(out / f"{name}.joints.npy", npy_bytes(positions))
            export_motion(out / name, positions, module.representation.skeleton, fps, preview=False,  # BVH
                          clean_contacts=args.clean_contacts)
            records.append({"file": name, "prompt": prompt, "repeat": k, "batch_seed": seed})
            previews.append((positions, prompt or "unconditional"))
    settings = {
        "command": "omg generate " + shlex.join(argv),
        "ckpt": str(args.ckpt),
        "module": type(module).__name__,
        "unconditional": not prompts,
        "prompts": prompts,
        "num_samples": args.num_samples,
        "length_s": args.length,
        "frames": frames,
        "fps": fps,
        "steps": args.steps,
        "sampler": "ddim, eta=0",
        "guidance_scale": (args.guidance if args.guidance is not None else module.hparams.get("guidance_scale")) if prompts else None,
        "seed": args.seed,
        "batch_size": args.batch_size,
        "ema": not args.no_ema,
        "clean_contacts": args.clean_contacts,
        "representation": module.spec["representation"],
        "skeleton": module.spec["skeleton"],
        "samples": records,
    }
    write_json(out / "generation.json", settings)
    if not args.no_preview:  # the first motions side by side with their captions
        shown = previews[:args.preview_count]
        render_gif(out / "preview.gif", [m for m, _ in shown], module.representation.skeleton, fps, titles=[t for _, t in shown])
    return settings
