"""``omg convert-ckpt``: a DeepSpeed or Lightning checkpoint as one fp32 (or EMA) safetensors file
(``omg.lit.checkpoint.convert``), which inference and fine-tuning load without DeepSpeed."""

from __future__ import annotations

from pathlib import Path

from omg.tools.args import run


def convert_ckpt(src: Path, dst: Path, ema: bool = False) -> dict:
    """Turn a DeepSpeed/Lightning checkpoint into one fp32 (or EMA) safetensors file.

    Args:
        src: a DeepSpeed checkpoint directory, a Lightning .ckpt or a converted .safetensors
        dst: the .safetensors file to write
        ema: write the EMA weights instead of the trained ones

    Returns:
        What was written: path, parameters, ema_weights, bytes and module_class.
    """
    from omg.lit.checkpoint import convert

    s = convert(src, dst, ema=ema)
    print(f"wrote {s['path']}: {s['parameters'] / 1e6:.2f}M parameters, {'EMA' if s['ema_weights'] else 'trained'} "
          f"fp32 weights, {s['bytes'] / 2**20:.1f} MiB ({s['module_class']})")
    return s


def main(argv: list[str]) -> None:
    run(convert_ckpt, argv, "omg convert-ckpt", as_positional=True)
