"""The one writer of generated motion, for every family and command (``omg generate``, ``omg transfer``,
``omg serve``): each motion's features, joints and BVH or glTF file, its companions, a preview and the
settings that reproduce it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omg.errors import UsageError
from omg.files import atomic_write, npy_bytes, removing_created, write_json
from omg.generation.protocol import GeneratedMotion, GenerationCard

MAX_PREVIEW = 6


def output_files(names: str, format: str, settings_file: str, preview: bool) -> tuple[str, ...]:
    """Glob patterns of the files ``write_generation`` writes for motions named like ``names``."""
    return (f"{names}.*.npy", f"{names}.{format}", settings_file, *(("preview.gif",) if preview else ()))


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
    from omg.export import export_motion
    from omg.io.fbx import one_blender_run
    from omg.skeleton import get_skeleton

    skeleton, fps = get_skeleton(card.skeleton), card.fps
    existing = set(out.iterdir()) if out.is_dir() else set()
    try:
        with removing_created(out):
            out.mkdir(parents=True, exist_ok=True)
            records, shown = [], []
            with one_blender_run():  # onto an FBX character: the motions in one Blender run
                for i, motion in enumerate(motions):
                    name = names[i] if names else f"sample_{i:03d}"
                    atomic_write(out / f"{name}.features.npy", npy_bytes(np.asarray(motion.features, np.float32)))
                    atomic_write(out / f"{name}.joints.npy", npy_bytes(np.asarray(motion.joints, np.float32)))
                    for stem, joints, _, title in motion.companions:
                        companion = np.asarray(joints, np.float32)
                        atomic_write(out / f"{stem.format(stem=name)}.joints.npy", npy_bytes(companion))
                        if title is not None and i < preview_count:
                            shown.append((joints, title))
                    export_motion(out / name, motion.joints, skeleton, fps, preview=False, rig=rig,
                                  clean_contacts=clean_contacts, joint_map=joint_map, format=format,
                                  rotations=motion.rotations)
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
