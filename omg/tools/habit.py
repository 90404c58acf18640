"""``omg transfer``: move a quadruped motion onto another species, with that species' habits.

The source (BVH, DeepMimic or ``.npy``) is retargeted onto SMAL-35 and encoded as ``quatvel``
features; the habit VQ-VAE re-encodes it with the target category's habit latent (a sample of
its flow prior: the checkpoint's own in the default training order, ``--prior_ckpt``'s in
``kl_then_flows``, where without it the mean of its posterior) and text embedding and
decodes it. A target the model does not know is described by the species book (or by the text
given); its habit latent is that of the known category whose description is nearest (Euclidean, the
paper's retrieval), while its own description's embedding stays the condition (the paper swaps only
the habit latent); the output says which category and at what distance. Written to ``--out``:
``transfer.features.npy`` (T, D), ``transfer.joints.npy`` (T, J, 3) with the target category's
mean bone offsets, ``transfer.bvh`` (SMAL-35 with those proportions and the model's rotations as they
are, no IK; with ``--to_rig`` on that rig;
``transfer.glb`` with ``--format glb``), ``source.joints.npy``,
``preview.gif`` (source and result side by side) and ``transfer.json`` (every setting).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from omg.errors import UsageError
from omg.files import check_output_dir
from omg.lit.generative import GenerationRequest
from omg.retarget import read_rig
from omg.tools.args import PositiveFiniteFloat, Seed, run
from omg.tools.export import OutputFormat
from omg.tools.generate import check_finite_motions, output_files, write_generation


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
        ckpt: the HabitVQModule checkpoint (in the default order ``flow_prior`` it holds the flow priors)
        prior_ckpt: the HabitPriorModule checkpoint (stage 2 of ``kl_then_flows``): the habit latent is a sample
            of the target's flow prior; without it, the checkpoint's own flows (``flow_prior``) or the mean of the
            target's posterior
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

    out = check_output_dir(out, files=(*output_files("transfer", format, "transfer.json", preview), "source.*.npy"))
    if to_rig_joint_map is not None and to_rig is None:
        raise UsageError("--to_rig_joint_map names the map of the --to_rig rig; give --to_rig RIG.bvh with it")
    module = load_module(ckpt, default_class=HabitVQModule, expect=HabitVQModule)
    card = module.generation_card()
    rig = read_rig(to_rig, card.skeleton, to_rig_joint_map) if to_rig is not None else None
    prior = None
    if prior_ckpt is not None:
        prior = load_module(prior_ckpt, default_class=HabitPriorModule, expect=HabitPriorModule)
        if prior.categories != module.categories:
            raise UsageError(f"--prior_ckpt {prior_ckpt} was fitted for categories {prior.categories}, --ckpt {ckpt} "
                             f"knows {module.categories}: fit the prior on this VQ-VAE")
    source_motion = module.read_source(Path(source), joint_map)
    request = GenerationRequest(prompts=None, frames=len(source_motion["features"]), seed=seed, species=to,
                                source=source_motion, options={"species_file": species_file,
                                                               "temperature": temperature, "quantizer": quantizer})
    settings = {"command": command, "source": str(source), **module.generation_settings(request, prior),
                "ckpt": str(ckpt), "prior_ckpt": str(prior_ckpt) if prior_ckpt else None, "seed": seed,
                "fps": card.fps, "skeleton": card.skeleton, "representation": card.representation,
                "to_rig": str(to_rig) if to_rig is not None else None, format: str(out / f"transfer.{format}")}
    motions = module.transfer_motions(request, prior)
    check_finite_motions(motions, ckpt)
    write_generation(out, motions, card, settings, names=["transfer"], settings_file="transfer.json", rig=rig,
                     joint_map=to_rig_joint_map, format=format, preview=preview)
    via = (f" via the nearest known category {settings['category']} (text distance {settings['distance']:.3f})"
           if settings["retrieved"] else "")
    print(f"transferred {Path(source).name} ({settings['frames']} frames at {card.fps:g} fps) to {to}{via}: {out}")
    return settings


def main(argv: list[str]) -> None:
    run(transfer, argv, "omg transfer", positional="source", nargs=None)
