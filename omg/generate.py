"""``omg generate``: sample motions from a checkpoint and write them with their settings.

Per sample it writes ``sample_NNN.features.npy`` (T, D) in the checkpoint's representation
(HumanML3D-compatible for humanml3d263) and ``sample_NNN.joints.npy`` (T, J, 3) joint
positions in metres, Y up; ``generation.json`` records every setting, so that a result can
be reproduced exactly.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import torch

from omg.cli import ToolParser
from omg.data.shards import atomic_write, npy_bytes, write_json
from omg.errors import UsageError

MAX_SECONDS = 60.0


def parse_args(argv: list[str]):
    p = ToolParser(prog="omg generate", description="Generate motions from a trained checkpoint.")
    p.add_argument("prompts", nargs="*", help="text prompts (needs a text-conditioned checkpoint)")
    p.add_argument("--ckpt", required=True, help="a .ckpt file, a DeepSpeed checkpoint directory or a .safetensors file")
    p.add_argument("--unconditional", action="store_true", help="sample the pretrained motion prior without text")
    p.add_argument("--num-samples", type=int, default=4, help="motions per prompt (or in total when unconditional)")
    p.add_argument("--length", type=float, default=6.0, help="seconds per motion")
    p.add_argument("--steps", type=int, default=200, help="DDIM steps")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--no-ema", action="store_true", help="use the trained weights instead of their EMA")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", default="out/generate")
    return p.parse_args(argv)


def main(argv: list[str]) -> None:
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import PretrainModule

    args = parse_args(argv)
    if not args.unconditional and not args.prompts:
        raise UsageError("give a prompt, or --unconditional to sample the motion prior")
    if args.num_samples < 1 or args.steps < 1:
        raise UsageError(f"--num-samples and --steps must be positive, got {args.num_samples}, {args.steps}")
    module = load_module(args.ckpt, default_class=PretrainModule, use_ema=not args.no_ema).to(args.device).eval()
    if args.prompts and type(module) is PretrainModule:
        raise UsageError(f"{args.ckpt} is an unconditional pretraining checkpoint: pass --unconditional, "
                         "or a text-conditioned (ControlNet) checkpoint for prompts")
    fps = module.spec["fps"]
    frames = round(args.length * fps)
    if not 0 < args.length <= MAX_SECONDS or frames < 2:
        raise UsageError(f"--length must be in (0, {MAX_SECONDS}] seconds and give at least 2 frames at {fps} fps, got {args.length}")

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for start in range(0, args.num_samples, args.batch_size):
        num = min(args.batch_size, args.num_samples - start)
        features = module.sample(num, frames, steps=args.steps, seed=args.seed + start, use_ema=False)  # (n, T, D)
        joints = module.representation.decode(features.float())  # (n, T, J, 3)
        for i in range(num):
            name = f"sample_{written:03d}"
            atomic_write(out / f"{name}.features.npy", npy_bytes(features[i].cpu().numpy().astype(np.float32)))
            atomic_write(out / f"{name}.joints.npy", npy_bytes(joints[i].cpu().numpy().astype(np.float32)))
            written += 1
    settings = {
        "command": "omg generate " + shlex.join(argv),
        "ckpt": str(args.ckpt),
        "unconditional": args.unconditional,
        "prompts": args.prompts,
        "num_samples": args.num_samples,
        "length_s": args.length,
        "frames": frames,
        "fps": fps,
        "steps": args.steps,
        "sampler": "ddim, eta=0",
        "seed": args.seed,
        "batch_size": args.batch_size,
        "seeds": "batch k uses seed + k * batch_size",
        "ema": not args.no_ema,
        "representation": module.spec["representation"],
        "skeleton": module.spec["skeleton"],
    }
    write_json(out / "generation.json", settings)
    print(f"wrote {written} motions of {frames} frames ({args.length} s at {fps} fps) to {out}")
    print(json.dumps({k: settings[k] for k in ("seed", "steps", "ema")}))
