"""``omg transfer``: move a quadruped motion onto another species, with that species' habits.

The source (BVH, DeepMimic or ``.npy``) is retargeted onto SMAL-35 and encoded as ``quatvel``
features; the habit VQ-VAE re-encodes it with the target category's habit latent (a sample of
its flow prior, or without ``--prior_ckpt`` the mean of its posterior) and text embedding and
decodes it. A target the model does not know is described by the species book (or by the text
given); its habit latent is that of the known category whose description is nearest (Euclidean, the
paper's retrieval), while its own description's embedding stays the condition (the paper swaps only
the habit latent); the output says which category and at what distance. Written to ``--out``:
``transfer.features.npy`` (T, D), ``transfer.joints.npy`` (T, J, 3) with the target category's
mean bone offsets, ``transfer.bvh`` (SMAL-35 with those proportions; with ``--to_rig`` on that rig;
``transfer.glb`` with ``--format glb``), ``source.joints.npy``,
``preview.gif`` (source and result side by side) and ``transfer.json`` (every setting).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import atomic_write, check_output_dir, file_problem, npy_bytes, write_json
from omg.retarget import read_rig
from omg.tools.args import PositiveFiniteFloat, Seed, run
from omg.tools.common import removing_created
from omg.tools.export import OutputFormat


def read_source(path: Path, module, joint_map: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """A motion file as the model's features: (features (T, D), source offsets (J, 3), root start (3,),
    the source's category). ``.npy``: quatvel features (T, D) or SMAL-35 joint positions (T, J, 3) at
    the model's frame rate; other files are read and retargeted onto the model's skeleton."""
    from omg.motion import Clip

    skeleton, fps = module.representation.skeleton, module.spec.fps
    if problem := file_problem(path):
        raise UsageError(f"SOURCE {path}: {problem}")
    if path.suffix.lower() == ".npy":
        try:
            array = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise UsageError(f"SOURCE {path}: not a readable .npy array ({e})") from None
        if array.dtype.kind in "fc" and not np.isfinite(array).all():  # the model would sample from NaN
            raise UsageError(f"SOURCE {path}: holds NaN or inf values ({int((~np.isfinite(array)).sum())} of "
                             f"{array.size}); give finite motion")
        J, D = skeleton.num_joints, module.spec.feature_dim
        if array.ndim == 2 and array.shape[1] == D:
            return (array.astype(np.float32), np.asarray(skeleton.rest_offsets, np.float32), np.zeros(3, np.float32),
                    "")
        if array.ndim == 3 and array.shape[1:] == (J, 3):  # the representation solves the rotations (IK)
            clip = Clip(id=path.stem, skeleton=skeleton, fps=fps, positions=array.astype(np.float32))
        else:
            raise UsageError(f"SOURCE {path}: a .npy source holds quatvel features (T, {D}) or {skeleton.name} joint "
                             f"positions (T, {J}, 3), got shape {array.shape}")
    else:
        from omg.io.read import read_motion
        from omg.retarget import retarget

        clip = retarget(read_motion(path), skeleton, joint_map=joint_map, fps=fps)
    if len(clip.positions) < 2:
        raise UsageError(f"SOURCE {path}: {len(clip.positions)} frame(s), need 2 or more")
    features, meta = module.representation.encode(clip)
    return (features, np.asarray(meta["offsets"], np.float32), np.asarray(meta["root_start"], np.float32),
            clip.category or "")


def resolve_target(module, to: str, species_file: Path | None) -> dict:
    """The category whose habits are used: ``to`` itself when known, else the known category whose
    description is nearest ``to``'s (a species of the book, or a description of 3 words or more); an
    unseen species keeps its own description's embedding as the condition (``embedding``)."""
    from omg.text.species import SpeciesBook, nearest_category, sentence_embeddings, species_key

    if not to or not to.strip():
        raise UsageError("--to is empty: give a species name (e.g. horse) or a description of the animal")
    key = species_key(to) if len(to.split()) < 3 else to
    if key in module.categories:
        return {"target": to, "category": key, "retrieved": False, "distance": 0.0}
    book = SpeciesBook.load(species_file)
    description = book.describe(to)
    from omg.text.base import build_text_encoder

    hp = module.hparams
    encoder = build_text_encoder(hp.get("text_encoder", "minilm"), **(hp.get("text_encoder_args") or {}))
    known = {name: module.descriptions.get(name) or book.description(name) for name in module.categories}
    name, distance = nearest_category(encoder, description, known)
    with torch.no_grad():
        embedding = sentence_embeddings(encoder, [description])[0].cpu()  # as the categories' were embedded
    return {"target": to, "description": description, "category": name, "retrieved": True, "distance": distance,
            "embedding": embedding}


def transfer(
    source: Path,
    *,
    to: str,
    ckpt: Path,
    prior_ckpt: Path | None = None,
    species_file: Path | None = None,
    joint_map: str | None = None,
    seed: Seed = 0,
    temperature: PositiveFiniteFloat = 1.0,
    quantizer: Literal["soft", "nearest"] | None = None,
    preview: bool = True,
    to_rig: Path | None = None,
    to_rig_joint_map: str | None = None,
    format: OutputFormat = "bvh",
    out: Path = Path("out/transfer"),
    command: str = "",
) -> dict:
    """Transfer a quadruped motion onto another species with its habits.

    Args:
        source: a BVH, DeepMimic (.json/.txt) or .npy (quatvel features or SMAL-35 joint positions) motion
        to: the target species: a known category (e.g. horse), a species of the species book, or a description
        ckpt: the HabitVQModule checkpoint (stage 1)
        prior_ckpt: the HabitPriorModule checkpoint (stage 2): the habit latent is a sample of the target's
            flow prior; without it, the mean of the target's posterior
        species_file: a YAML of extra species descriptions (name: description)
        joint_map: the source rig's joint map (a registered name or a YAML file; default: detected)
        seed: random seed (prior sample and soft quantization)
        temperature: scale of the prior's base Gaussian
        quantizer: soft or nearest (default: the checkpoint's)
        preview: write preview.gif (source and transfer side by side)
        to_rig: write the transfer onto this BVH file's quadruped rig (its hierarchy, names, channels, unit)
        to_rig_joint_map: the --to_rig rig's joint map (a registered name or a YAML file; default: detected;
            --joint_map is the source's)
        format: bvh, or glb (glTF 2.0 binary: joint nodes, a skin and the animation)
        out: output folder (created; files in it are overwritten)
        command: the command line, recorded in transfer.json

    Returns:
        The settings written to transfer.json.
    """
    from omg.lit.checkpoint import load_module
    from omg.lit.habit import HabitPriorModule, HabitVQModule

    out = check_output_dir(out)
    if to_rig_joint_map is not None and to_rig is None:
        raise UsageError("--to_rig_joint_map names the map of the --to_rig rig; give --to_rig RIG.bvh with it")
    module = load_module(ckpt, default_class=HabitVQModule, expect=HabitVQModule)
    rig = read_rig(to_rig, module.representation.skeleton, to_rig_joint_map) if to_rig is not None else None
    prior = None
    if prior_ckpt is not None:
        prior = load_module(prior_ckpt, default_class=HabitPriorModule, expect=HabitPriorModule)
        if prior.categories != module.categories:
            raise UsageError(f"--prior_ckpt {prior_ckpt} was fitted for categories {prior.categories}, --ckpt {ckpt} "
                             f"knows {module.categories}: fit the prior on this VQ-VAE")
    features, source_offsets, root_start, source_category = read_source(Path(source), module, joint_map)
    target = resolve_target(module, to, species_file)
    k = module.categories.index(target["category"])
    torch.manual_seed(seed)
    if prior is not None:
        z = prior.habit_latents(k, 1, seed=seed, temperature=temperature)
    else:
        z = module.mean_habit(k)[None]
    # the paper's transfer for an unseen species: the retrieved category's habit latent, the species' own text
    result = module.transfer(torch.from_numpy(features)[None], k, z, seed=seed, quantizer=quantizer,
                             text=target.get("embedding"))[0]
    if not torch.isfinite(result).all():
        raise UsageError(f"the model produced NaN or inf motion: a diverged checkpoint ({ckpt})")
    rep, fps = module.representation, module.spec.fps
    offsets = module.category_offsets(k)
    start = torch.from_numpy(root_start)
    joints = rep.decode(result.float(), offsets, start).numpy().astype(np.float32)
    source_joints = rep.decode(torch.from_numpy(features), torch.from_numpy(source_offsets), start).numpy()
    settings = {
        "command": command, "source": str(source), "source_category": source_category, "to": to,
        "category": target["category"], "retrieved": target["retrieved"], "distance": target["distance"],
        "description": target.get("description"),
        "condition": "its own description" if target["retrieved"] else f"{target['category']}'s description",
        "ckpt": str(ckpt), "prior_ckpt": str(prior_ckpt) if prior_ckpt else None,
        "habit": "prior sample" if prior is not None else "posterior mean", "seed": seed,
        "temperature": temperature, "quantizer": quantizer or module.vqvae.quantizer.mode, "frames": len(joints),
        "fps": fps, "skeleton": rep.skeleton.name, "representation": "quatvel",
        "target_offsets": offsets.tolist(), "to_rig": str(to_rig) if to_rig is not None else None,
    }
    from omg.export import export_motion

    with removing_created(out):
        out.mkdir(parents=True, exist_ok=True)
        atomic_write(out / "transfer.features.npy", npy_bytes(result.float().numpy()))
        atomic_write(out / "transfer.joints.npy", npy_bytes(joints))
        atomic_write(out / "source.joints.npy", npy_bytes(source_joints.astype(np.float32)))
        settings[format] = export_motion(out / "transfer", joints, rep.skeleton, fps, preview=False, rig=rig,
                                         joint_map=to_rig_joint_map, format=format)[format]
        if preview:
            from omg.io.render import render_gif

            how = (f"{target['category']}'s habits (nearest known, distance {target['distance']:.3f})"
                   if target["retrieved"] else f"{target['category']}'s habits")
            render_gif(out / "preview.gif", [source_joints, joints], rep.skeleton, fps,
                       titles=[f"source: {Path(source).name}", f"{to}: {how}"])
        write_json(out / "transfer.json", settings)
    via = (f" via the nearest known category {target['category']} (text distance {target['distance']:.3f})"
           if target["retrieved"] else "")
    print(f"transferred {Path(source).name} ({len(joints)} frames at {fps:g} fps) to {to}{via}: {out}")
    return settings


def main(argv: list[str]) -> None:
    run(transfer, argv, "omg transfer", positional="source", nargs=None)
