"""``omg bench character``: a generation's motions written onto a user's FBX character."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from omg.errors import UsageError
from omg.tools.args import PositiveInt

FPS = 20.0


def bench_character(fbx: Path, motions: PositiveInt = 8, frames: PositiveInt = 120,
                    command: str = "omg bench character") -> dict:
    """Seconds to write motions onto an FBX character (``omg generate --to_rig CHARACTER.fbx``), each in a
    Blender run of its own against all of them in one run (``omg.io.fbx.one_blender_run``, as ``omg generate``
    and the server write a generation). The motions are procedural walks (``omg.data.synth``) cut to
    ``frames`` and retargeted onto the character. Prints one Markdown table row.

    Args:
        fbx: the character, a skinned binary .fbx file
        motions: how many motions are written
        frames: frames per motion, at 20 fps (a walk shorter than that is written whole)
        command: the command line, printed with the results

    Returns:
        The row: motions, mean frames, seconds a run each, seconds one run.
    """
    from omg.data.synth import synth_clip
    from omg.io.fbx import one_blender_run, read_character, write_character
    from omg.retarget import onto_rig

    if Path(fbx).suffix.lower() != ".fbx":
        raise UsageError(f"--fbx {fbx}: give an .fbx character (the writes this measures go through Blender)")
    rig = read_character(fbx, "--fbx")
    # synth's human actions cycle with the clip's index, walk first: every tenth clip is a walk
    walks = [synth_clip("human", 10 * k, fps=FPS)[0].positions[:frames] for k in range(motions)]
    moved = [onto_rig(walk, "smpl22", rig, FPS) for walk in walks]
    with tempfile.TemporaryDirectory(prefix="omg-bench-character-") as folder:
        start = time.perf_counter()
        for k, motion in enumerate(moved):
            write_character(Path(folder) / f"each_{k}.fbx", motion)
        each = time.perf_counter() - start
        start = time.perf_counter()
        with one_blender_run():
            for k, motion in enumerate(moved):
                write_character(Path(folder) / f"one_{k}.fbx", motion)
        one = time.perf_counter() - start
    row = {"motions": motions, "frames": sum(len(w) for w in walks) / motions, "each_s": each, "one_s": one}
    print("| character | motions | frames | a Blender run each, s | one run for all, s | speed-up |\n"
          "|---|---:|---:|---:|---:|---:|")
    print(f"| {Path(fbx).name} | {motions} | {row['frames']:.0f} | {each:.1f} | {one:.1f} | {each / one:.1f}x |")
    print(f"\n`{command}`")
    return row
