"""``omg bench rig``: real clips through the model skeletons and back onto their own rigs."""

from __future__ import annotations

from pathlib import Path

from omg.errors import UsageError

# public rigs with no clip in the shared data are a real CMU clip renamed into their naming
_CMU_SPINE = {"LowerBack": "Spine", "Spine": "Spine1", "Spine1": "Spine2"}
_CMU_TOES = {"LeftToeBase": "LeftToe", "RightToeBase": "RightToe"}
RENAMED_CMU = {
    "lafan1": {**_CMU_SPINE, **_CMU_TOES},
    "mixamo": {n: f"mixamorig:{_CMU_SPINE.get(n, n)}" for n in (
        "Hips", "LowerBack", "Spine", "Spine1", "Neck", "Head", "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand",
        "RightShoulder", "RightArm", "RightForeArm", "RightHand", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
        "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase")},
    "style100": {"LowerBack": "Chest", "Spine": "Chest2", "Spine1": "Chest3", "Neck": "Chest4", "Neck1": "Neck",
                 **{f"{s}{a}": f"{s}{b}" for s in ("Left", "Right") for a, b in (
                     ("Shoulder", "Collar"), ("Arm", "Shoulder"), ("ForeArm", "Elbow"), ("Hand", "Wrist"),
                     ("UpLeg", "Hip"), ("Leg", "Knee"), ("Foot", "Ankle"), ("ToeBase", "Toe"))}},
}  # fmt: skip
# (label, file under the motion data folder, model skeleton, joint map, renaming of the CMU rig)
RIG_CLIPS = [
    ("Bandai-Namco", "human/bandai1/dataset-1_walk_normal_001.bvh", "smpl22", "bandai", None),
    ("Bandai-Namco", "human/bandai2/dataset-2_run_normal_001.bvh", "smpl22", "bandai", None),
    ("CMU (cgspeed BVH)", "human/cmu/02_01.bvh", "smpl22", "cmu", None),
    ("DeepMimic humanoid", "human/deepmimic/humanoid3d_walk.txt", "smpl22", "deepmimic_humanoid", None),
    ("LaFAN1 (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "lafan1", "lafan1"),
    ("100STYLE (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "style100", "style100"),
    ("Mixamo (CMU 02_01 renamed)", "human/cmu/02_01.bvh", "smpl22", "mixamo", "mixamo"),
    ("MANN dog", "quadruped/mann_dog/D1_004_KAN01_001.bvh", "smal35", "mann_dog", None),
    ("DeepMimic dog", "quadruped/deepmimic_dog/dog3d_trot.txt", "smal35", "deepmimic_dog", None),
]


def rig_round_trips(data: Path) -> list[dict]:
    """``omg.retarget.rig_round_trip`` for every row of ``RIG_CLIPS`` whose file is under ``data``."""
    from dataclasses import replace

    from omg.io.read import read_motion
    from omg.retarget import rig_round_trip

    rows = []
    for label, rel, skeleton, jmap, rename in RIG_CLIPS:
        if not (Path(data) / rel).exists():
            continue
        rig = read_motion(Path(data) / rel)
        if rename:
            rig = replace(rig, names=[RENAMED_CMU[rename].get(n, n) for n in rig.names])
        rows.append({"label": label, "file": rel, **rig_round_trip(rig, skeleton, jmap)})
    return rows


def bench_rig(data: Path) -> list[dict]:
    """Round trip of real clips through the model skeletons and back onto their own rigs
    (``omg.retarget.rig_round_trip``): import onto SMPL-22 / SMAL-35, ``onto_rig`` back, errors
    against the original after one translation. Prints one Markdown row per rig.

    Args:
        data: the motion data folder (../shared/data/motion: human/, quadruped/)

    Returns:
        One row per rig: label, file, and the round trip's figures.
    """
    if not Path(data).is_dir():
        raise UsageError(f"--data {data}: not a folder (the motion data folder, e.g. ../shared/data/motion)")
    rows = rig_round_trips(data)
    if not rows:
        raise UsageError(f"--data {data}: none of the benchmark's clips is there ({RIG_CLIPS[0][1]}, ...)")
    print("| rig | clip | joints (map points) | frames | mean error cm | max error cm | mapped joints mean cm "
          "| bone length change cm | foot slide cm/s original -> back | feet off the ground cm median / 95 % "
          "| worst foot off the ground cm median / 95 % |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['label']} | {Path(r['file']).name} | {r['joints']} ({r['mapped']}) | {r['frames']} "
              f"| {r['mean_cm']:.2f} | {r['max_cm']:.2f} | {r['mapped_mean_cm']:.2f} | {r['bone_cm']:.2f} "
              f"| {r['slide_original_cm_s']:.1f} -> {r['slide_back_cm_s']:.1f} "
              f"| {r['ground_cm']:.2f} / {r['ground_p95_cm']:.2f} | {r['foot_cm']:.2f} / {r['foot_p95_cm']:.2f} |",
              flush=True)
    return rows
