"""``omg export``: BVH or glTF files (and GIF previews) of motions: joint positions solved to local
rotations by IK (``omg.export``), or features decoded by their representation first.

A folder written by ``omg generate`` brings its settings (generation.json: skeleton, frame rate,
representation and the prompts, which become the previews' captions).
"""

from __future__ import annotations

import json
import math
import os
import re
import time
from pathlib import Path
from typing import Literal

from omg.errors import UsageError
from omg.export import EULER_ORDERS, FORMATS, export_motion, output_format
from omg.files import check_output_dir, read_text
from omg.generation.read import read_positions
from omg.retarget import read_rig
from omg.skeleton import get_skeleton
from omg.tools.args import PositiveFiniteFloat, run

DEFAULT_FPS = 20.0
DEFAULT_SKELETON = "smpl22"
EulerOrder = Literal[EULER_ORDERS]  # type: ignore[valid-type]
OutputFormat = Literal[FORMATS]  # type: ignore[valid-type]


def export(
    inputs: list[Path],
    *,
    skeleton: str | None = None,
    fps: PositiveFiniteFloat | None = None,
    representation: str | None = None,
    order: EulerOrder = "ZXY",
    scale: PositiveFiniteFloat = 1.0,
    preview: bool = True,
    out: Path | None = None,
    clean_contacts: bool = False,
    to_rig: Path | None = None,
    joint_map: str | None = None,
    format: OutputFormat | None = None,
) -> list[dict]:
    """Write BVH files (and GIF previews) of generated motions.

    Every input is read and checked before anything is written; a failed export leaves none of
    the files it created.

    Args:
        inputs: directories (of *.joints.npy, else *.features.npy) or .npy files
        skeleton: skeleton name (default: generation.json's, else smpl22)
        fps: frames per second (default: generation.json's, else 20)
        representation: decode *.features.npy with this representation (e.g. humanml3d263)
        order: Euler order of the BVH rotation channels
        scale: BVH units per metre (100 for centimetres)
        preview: write a GIF preview beside each BVH file
        out: write the files into this folder (default: beside each input)
        clean_contacts: pin planted feet (removes foot skating) before IK
        to_rig: write the motions onto this rig: a BVH file's (its hierarchy, names, channels, unit, rest pose),
            a skinned glTF character (.glb, .gltf: the character, its mesh and materials kept), or an FBX
            character (.fbx, read and written by Blender: pip install 'omg[fbx]')
        joint_map: the rig's joint map for --to_rig (a registered name or a YAML file; default: detected
            from its joint names, as on import)
        format: bvh, glb (glTF 2.0 binary: joint nodes, a skin and the animation; onto a character, the
            character with the animation added) or fbx (onto an FBX character, the character with the
            animation added); default: glb with a .glb/.gltf --to_rig, fbx with an .fbx one, else bvh

    Returns:
        What was written per input (``export_motion``'s reports).
    """
    if representation is not None:
        from omg.registry import REPRESENTATIONS

        REPRESENTATIONS.get(representation)  # an unknown name is a UsageError naming the known ones
    if skeleton is not None:
        get_skeleton(skeleton)
    out = check_output_dir(out) if out else None
    if joint_map is not None and to_rig is None:
        raise UsageError("--joint_map names the map of the --to_rig rig; give --to_rig RIG (.bvh, .glb, .gltf, "
                         ".fbx) with it")
    format = output_format(format, to_rig)
    rigs: dict = {}  # skeleton name -> the rig, read and checked once before anything is written
    jobs = []  # every file is read and checked before anything is written
    for path in [f for spec in inputs for f in _inputs(spec)]:
        settings = _settings(path.parent)
        skel = get_skeleton(skeleton or settings.get("skeleton") or DEFAULT_SKELETON)
        rate = fps or settings.get("fps") or DEFAULT_FPS
        decode = (representation or settings.get("representation")) if path.name.endswith(".features.npy") else None
        if path.name.endswith(".features.npy") and decode is None:
            raise UsageError(f"{path}: a features file needs --representation (e.g. humanml3d263)")
        positions = read_positions(path, skel, rate, decode)  # joints, or features decoded to them
        stem = path.with_name(re.sub(r"(\.joints|\.features)?\.npy$", "", path.name))
        if out:
            stem = out / stem.name
        if to_rig is not None and skel.name not in rigs:
            rigs[skel.name] = read_rig(to_rig, skel, joint_map)
        jobs.append((path, stem, positions, skel, rate, _prompt(settings, stem.name)))
    extensions = (format, "gif") if preview else (format,)
    targets = [stem.with_name(f"{stem.name}.{ext}") for _, stem, *_ in jobs for ext in extensions]
    for target in targets:
        if target.is_dir():
            raise UsageError(f"{target}: a folder is in the way of the output file; move it or export elsewhere")
        if target.parent.exists() and not os.access(target.parent, os.W_OK | os.X_OK):
            raise UsageError(f"{target.parent}: not writable; copy the motions to a folder you can write to")
    if len({t for t in targets}) < len(targets):
        raise UsageError("two inputs have the same name and would be written to the same --out file; export them apart")
    new = [t for t in targets if not t.exists()]
    created = out is not None and not out.exists()
    reports = []
    try:
        if created:
            out.mkdir(parents=True)
        for path, stem, positions, skel, rate, texts in jobs:
            start = time.perf_counter()
            report = export_motion(stem, positions, skel, rate, texts, preview, order, scale, clean_contacts,
                                   rig=rigs.get(skel.name), joint_map=joint_map, format=format)
            reports.append(report)
            written = ", ".join(Path(report[k]).name for k in (format, "gif") if k in report)
            how = f"on the rig of {to_rig}" if to_rig else f"IK error {report['ik_error_m'] * 1000:.3f} mm"
            print(f"{path}: {written} ({report['frames']} frames at {rate:g} fps, {how}, "
                  f"{time.perf_counter() - start:.1f} s)")  # fmt: skip
    except Exception:  # a failed export leaves none of the files it created
        for target in new:
            target.unlink(missing_ok=True)
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    return reports


def _inputs(spec: str) -> list[Path]:
    path = Path(spec)
    if path.is_dir():
        files = sorted(path.glob("*.joints.npy")) or sorted(path.glob("*.features.npy"))
        if not files:
            raise UsageError(f"{path}: no *.joints.npy or *.features.npy files to export")
        return files
    if not path.is_file() or path.suffix != ".npy":
        raise UsageError(f"{path}: not a directory or an existing .npy file")
    return [path]


def _settings(directory: Path) -> dict:
    """``omg generate``'s generation.json beside the motions, checked; {} when there is none."""
    path = directory / "generation.json"
    if not path.exists() and not path.is_symlink():
        return {}
    try:
        settings = json.loads(read_text(path, "settings file"))
    except json.JSONDecodeError as e:
        raise UsageError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(settings, dict):
        raise UsageError(f"{path}: expected a JSON object (omg generate's settings), "
                         f"got a JSON {type(settings).__name__}")
    for key in ("skeleton", "representation"):
        if settings.get(key) is not None and not isinstance(settings[key], str):
            raise UsageError(f"{path}: {key!r} must be a name, got {settings[key]!r}")
    fps = settings.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float))
                            or not math.isfinite(fps) or fps <= 0):
        raise UsageError(f"{path}: 'fps' must be a positive number, got {fps!r}; or pass --fps")
    prompts = settings.get("prompts")
    if prompts is not None and not (isinstance(prompts, list) and all(isinstance(p, str) for p in prompts)):
        raise UsageError(f"{path}: 'prompts' must be a list of strings, got {prompts!r}")
    num = settings.get("num_samples")
    if num is not None and (isinstance(num, bool) or not isinstance(num, int) or num < 1):
        raise UsageError(f"{path}: 'num_samples' must be a positive integer, got {num!r}")
    return settings


def _prompt(settings: dict, stem: str) -> list[str]:
    """``omg generate`` writes ``num_samples`` motions per prompt, named sample_NNN in order."""
    prompts, match = settings.get("prompts") or [], re.fullmatch(r"sample_(\d+)", stem)
    if not prompts or not match:
        return []
    index = int(match.group(1)) // max(int(settings.get("num_samples", 1)), 1)
    return [prompts[index]] if index < len(prompts) else []


def main(argv: list[str]) -> None:
    run(export, argv, "omg export", positional="inputs", nargs="+")
