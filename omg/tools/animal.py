"""``omg generate`` with an OmniMotionGPT checkpoint: text + a human motion -> animal motion.

The human motion comes from a file (``--from_motion``: BVH / ASF-AMC / DeepMimic retargeted to
smpl22, a ``.joints.npy``, or a features ``.npy``), from omg's own OMG ControlNet
(``--human_ckpt``, prompted with the sentence made about "a person"), or else from the
checkpoint's ``human_source``. Per motion: ``sample_NNN.features.npy`` (smal35 maa),
``sample_NNN.joints.npy``, ``sample_NNN.bvh`` (SMAL-35 with the animal's bone lengths, the
model's rotations written as they are), ``sample_NNN.human.joints.npy`` (the human motion it
came from), ``preview.gif`` and ``generation.json``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import atomic_write, file_problem, npy_bytes, write_json
from omg.motion import get_representation
from omg.tools.common import removing_created


def read_human_motion(path: Path, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """A human motion file -> smpl22 maa features (T, 138) and offsets (22, 3) at ``fps``."""
    from omg.lit.omgpt import HUMAN_SKELETON, maa_from_positions
    from omg.skeleton import get_skeleton

    path = Path(path)
    if problem := file_problem(path):
        raise UsageError(f"--from_motion {path}: {problem}")
    skeleton = get_skeleton(HUMAN_SKELETON)
    if path.suffix.lower() != ".npy":
        from omg.io.read import read_motion
        from omg.retarget import retarget

        clip = retarget(read_motion(path), HUMAN_SKELETON, fps=fps)
        features, meta = get_representation("maa", skeleton).encode(clip)
        return features, np.asarray(meta["offsets"], dtype=np.float32)
    try:
        array = np.load(path, allow_pickle=False).astype(np.float32)
    except (ValueError, OSError) as e:
        raise UsageError(f"--from_motion {path}: not a readable .npy file ({e})") from None
    maa_dim = (skeleton.num_joints + 1) * 6
    if array.ndim == 3 and array.shape[1:] == (skeleton.num_joints, 3):
        return maa_from_positions(array, fps)
    if array.ndim == 2 and array.shape[1] == maa_dim:
        return array, skeleton.rest_offsets.astype(np.float32)
    if array.ndim == 2 and array.shape[1] == 263:
        joints = get_representation("humanml3d263", skeleton).decode(torch.from_numpy(array)).numpy()
        return maa_from_positions(joints, fps)
    raise UsageError(f"--from_motion {path}: an array of shape {array.shape}; expected joints (T, 22, 3) or features "
                     f"(T, {maa_dim}) smpl22 maa or (T, 263) humanml3d263")


def generate_animal(module, prompts: list[str], *, ckpt: Path, animal: str | None, from_motion: Path | None,
                    human_ckpt: Path | None, num_samples: int, length: float, steps: int, sampler: str,
                    guidance: float | None, seed: int, preview: bool, preview_count: int, device: torch.device,
                    out: Path, command: str, to_rig: Path | None = None, joint_map: str | None = None,
                    format: str = "bvh") -> dict:
    from omg.export import export_motion
    from omg.io.bvh import write_bvh
    from omg.lit.omgpt import generate_human
    from omg.retarget import read_rig
    from omg.text.subjects import about_animal, choose_animal, to_person

    if not prompts:
        raise UsageError("an OmniMotionGPT checkpoint generates from prompts: give one (\"a dog jumps over a log\")")
    if from_motion is not None and human_ckpt is not None:
        raise UsageError("give --from_motion (a human motion file) or --human_ckpt (a ControlNet checkpoint), not both")
    names = module.animal_names
    rig = read_rig(to_rig, module.spec.skeleton, joint_map) if to_rig is not None else None  # checked before sampling
    chosen = [choose_animal(p, names, animal) for p in prompts]  # the rule of OmniMotionModule.sample
    fps = module.spec.fps
    frames = round(length * fps)
    module = module.to(device).eval()
    human_file = None
    if from_motion is not None:
        human_file = read_human_motion(from_motion, module.human_spec.fps)
        frames = min(frames, len(human_file[0])) if length else len(human_file[0])
        num_samples = 1  # the translation of a given motion is deterministic
    if frames < 2:
        raise UsageError(f"the motion has {frames} frame(s) at {fps:g} fps; need 2 or more")
    generator = None
    if human_ckpt is not None:
        from omg.lit.checkpoint import load_module
        from omg.lit.controlnet import ControlNetModule

        generator = load_module(human_ckpt, expect=ControlNetModule).to(device)
    jobs = [(p, a, k) for p, a in zip(prompts, chosen) for k in range(num_samples)]
    skeleton = module.representation.skeleton
    records, previews = [], []
    with removing_created(out):
        out.mkdir(parents=True, exist_ok=True)
        for index, (prompt, name, k) in enumerate(jobs):
            lengths = torch.tensor([frames])
            person = to_person(prompt, names)
            if human_file is not None:
                human = torch.from_numpy(human_file[0][:frames])[None]
                human_offsets = torch.from_numpy(human_file[1])[None]
            elif generator is not None:
                human, human_offsets = generate_human(generator, [person], lengths, seed + index, fps, steps=steps,
                                                      guidance=guidance, sampler=sampler)
            else:
                human, human_offsets = module.human_motion([person], lengths.to(device), seed + index)
            # use_ema=False: load_module has already put the EMA weights in (unless --no_ema)
            features = module.translate([prompt], human.to(device), human_offsets.to(device), lengths, [name],
                                        use_ema=False)[0]
            if not torch.isfinite(features).all():
                raise UsageError(f"the model produced NaN or inf motions: a diverged checkpoint ({ckpt})")
            offsets = module.animal_offsets(name).cpu()
            rotations, root = get_representation("maa", skeleton).rotations_and_root(features.cpu().float())
            joints = skeleton.forward_kinematics(rotations, root, offsets).numpy().astype(np.float32)
            human_joints = module.human_rep.decode(human[0].float().cpu(), human_offsets[0].cpu()).numpy()
            stem = f"sample_{index:03d}"
            atomic_write(out / f"{stem}.features.npy", npy_bytes(features.float().cpu().numpy()))
            atomic_write(out / f"{stem}.joints.npy", npy_bytes(joints))
            atomic_write(out / f"{stem}.human.joints.npy", npy_bytes(human_joints.astype(np.float32)))
            if rig is None and format == "bvh":  # the model's rotations as they are, no IK
                write_bvh(out / f"{stem}.bvh", skeleton, rotations.numpy(), root.numpy(), fps, offsets.numpy())
            else:  # onto the user's rig, or glTF
                export_motion(out / stem, joints, skeleton, fps, preview=False, rig=rig, joint_map=joint_map,
                              format=format)
            records.append({"file": stem, "prompt": prompt, "animal": name, "human_prompt": person, "repeat": k,
                            "animal_prompt": about_animal(prompt, name, names)})
            previews.append((joints, f"{prompt} ({name})"))
        settings = {
            "command": command, "ckpt": str(ckpt), "module": type(module).__name__, "prompts": prompts,
            "animal": animal, "from_motion": None if from_motion is None else str(from_motion),
            "human_ckpt": None if human_ckpt is None else str(human_ckpt),
            "human_source": "from_motion" if from_motion else "human_ckpt" if human_ckpt else module.human_source,
            "num_samples": num_samples, "frames": frames, "fps": fps, "steps": steps, "sampler": sampler,
            "guidance_scale": guidance, "seed": seed, "representation": module.spec.representation,
            "skeleton": module.spec.skeleton, "to_rig": None if to_rig is None else str(to_rig), "format": format,
            "samples": records,
        }
        write_json(out / "generation.json", settings)
        if preview:
            from omg.io.render import render_gif

            shown = previews[:preview_count]
            render_gif(out / "preview.gif", [m for m, _ in shown], skeleton, fps, titles=[t for _, t in shown])
    print(f"wrote {len(records)} animal motions of {frames} frames ({frames / fps:g} s at {fps:g} fps) to {out}")
    return settings
