"""``omg joint-map RIG``: a joint map to finish for a rig no registered map fits
(``omg.retarget.scaffold_joint_map``), printed or written as YAML."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from omg.tools.args import run


def joint_map(rig: Path, target: Literal["smpl22", "smal35"] | None = None, out: Path | None = None) -> dict[str, int]:
    """Print (or write) the YAML of the closest joint map for a rig, each joint matched, guessed or TODO.

    Args:
        rig: the rig: a BVH file (its HIERARCHY's joint names are what the map names) or a skinned glTF
            character (.glb, .gltf: its skin's joint nodes' names) or an FBX character (.fbx: its armature's
            bones' names, read by Blender: pip install 'omg[fbx]'); or a motion file whose clips are to be
            imported (a DeepMimic .txt/.json with its character file beside it, an ASF/AMC .amc)
        target: the model skeleton to map onto: smpl22 (humans) or smal35 (quadrupeds); default: that of
            the registered map closest to the rig
        out: the YAML file to write (default: print it)

    Returns:
        How many target joints were matched by name, guessed and left TODO.
    """
    from omg.errors import UsageError
    from omg.files import atomic_write, check_output_dir
    from omg.io.deepmimic import is_deepmimic_motion
    from omg.io.read import read_motion
    from omg.retarget import read_rig_file, scaffold_joint_map

    if rig.suffix.lower() not in (".txt", ".json", ".amc"):
        motion = read_rig_file(rig, what="RIG")
    elif not rig.is_file():
        raise UsageError(f"RIG {rig}: no such file")
    elif rig.suffix.lower() != ".amc" and not is_deepmimic_motion(rig):
        raise UsageError(f'RIG {rig}: not a DeepMimic motion (a JSON object with "Frames"); give a rig (.bvh, .glb, '
                         ".gltf, .fbx) or a motion file to import (DeepMimic .txt/.json, ASF/AMC .amc)")
    else:
        motion = read_motion(rig, what="RIG")
    text, counts = scaffold_joint_map(motion, target)
    if out is None:
        print(text, end="")
        return counts
    check_output_dir(out.parent, "--out")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, text.encode())
    print(f"wrote {out}: {counts['matched']} joints matched, {counts['guessed']} guessed (check them), "
          f"{counts['todo']} TODO; then pass it as --joint_map {out}")
    return counts


def main(argv: list[str]) -> None:
    run(joint_map, argv, "omg joint-map", as_positional=True)
