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

from omg.cli import ToolParser
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
    p.add_argument("--num-samples", type=int, default=4, help="motions per prompt (or in total when unconditional)")
    p.add_argument("--length", type=float, default=6.0, help="seconds per motion")
    p.add_argument("--steps", type=int, default=200, help="DDIM steps")
    p.add_argument("--guidance", type=float, help="classifier-free guidance scale s (default: the checkpoint's, OMG: 4.5)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--no-ema", action="store_true", help="use the trained weights instead of their EMA")
    p.add_argument("--no-preview", action="store_true", help="skip the GIF preview")
    p.add_argument("--clean-contacts", action="store_true", help="pin planted feet in the BVH files (removes foot skating)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", default="out/generate")
    return p.parse_args(argv)


def read_prompts(args) -> list[str]:
    prompts = list(args.prompts)
    if args.prompts_file:
        path = Path(args.prompts_file)
        if not path.is_file():
            raise UsageError(f"--prompts-file {path}: no such file")
        prompts += [line.strip() for line in path.read_text().splitlines() if line.strip()]
    if empty := [i for i, p in enumerate(prompts) if not p.strip()]:
        raise UsageError(f"prompt {empty[0] + 1} is empty; give a sentence such as \"a person walks forward\"")
    return prompts


def main(argv: list[str]) -> None:
    from omg.io.export import export_motion
    from omg.io.render import render_gif
    from omg.lit.checkpoint import load_module
    from omg.lit.controlnet import ControlNetModule
    from omg.lit.pretrain import MotionDiffusionModule, PretrainModule

    args = parse_args(argv)
    prompts = read_prompts(args)
    if args.unconditional == bool(prompts):
        raise UsageError("give prompts (or --prompts-file) for text-to-motion, or --unconditional to sample the motion prior")
    if args.num_samples < 1 or args.steps < 1 or args.batch_size < 1:
        raise UsageError(f"--num-samples, --steps and --batch-size must be positive, got {args.num_samples}, {args.steps}, {args.batch_size}")
    module = load_module(args.ckpt, default_class=PretrainModule, use_ema=not args.no_ema, expect=MotionDiffusionModule)
    module = module.to(args.device).eval()
    if prompts and not isinstance(module, ControlNetModule):
        raise UsageError(f"{args.ckpt} is an unconditional pretraining checkpoint: pass --unconditional, "
                         "or a text-conditioned (ControlNet) checkpoint for prompts")
    fps = module.spec["fps"]
    frames = round(args.length * fps)
    if not 0 < args.length <= MAX_SECONDS or frames < 2:
        raise UsageError(f"--length must be in (0, {MAX_SECONDS}] seconds and give at least 2 frames at {fps} fps, got {args.length}")

    # one job per motion: (prompt or None, sample index); batched in order
    jobs = [(p, k) for p in (prompts or [None]) for k in range(args.num_samples)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records, previews = [], []
    for start in range(0, len(jobs), args.batch_size):
        batch = jobs[start : start + args.batch_size]
        seed = args.seed + start
        if prompts:
            features = module.generate([p for p, _ in batch], frames, steps=args.steps, seed=seed, scale=args.guidance,
                                       use_ema=False)
        else:
            features = module.sample(len(batch), frames, steps=args.steps, seed=seed, use_ema=False)  # (n, T, D)
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
        shown = previews[:MAX_PREVIEW]
        render_gif(out / "preview.gif", [m for m, _ in shown], module.representation.skeleton, fps, titles=[t for _, t in shown])
    print(f"wrote {len(records)} motions of {frames} frames ({args.length} s at {fps} fps) to {out}")
