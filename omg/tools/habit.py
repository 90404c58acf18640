"""``omg transfer``: move a quadruped motion onto another species, with that species' habits.

A thin alias of ``omg generate`` on a habit checkpoint (``omg generate --ckpt VQ --from_motion SOURCE
--animal TO``), with transfer's flag names and files. The source (BVH, DeepMimic or ``.npy``) is
retargeted onto SMAL-35 and encoded as ``quatvel`` features; the habit VQ-VAE re-encodes it with the
target category's habit latent (a sample of its flow prior: the checkpoint's own in the default training
order, ``--prior_ckpt``'s in ``kl_then_flows``, where without it the mean of its posterior) and text
embedding and decodes it (``omg.generation.habit``). A target the model does not know is described by
the species book (or by the text given); its habit latent is that of the known category whose
description is nearest (Euclidean, the paper's retrieval), while its own description's embedding stays
the condition (the paper swaps only the habit latent); the output says which category and at what
distance. Written to ``--out``: ``transfer.features.npy`` (T, D), ``transfer.joints.npy`` (T, J, 3)
with the target category's mean bone offsets, ``transfer.bvh`` (SMAL-35 with those proportions and the
model's rotations as they are, no IK; with ``--to_rig`` on that rig; ``transfer.glb`` with ``--format
glb``), ``source.joints.npy``, ``preview.gif`` (source and result side by side) and ``transfer.json``
(every setting).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from omg.tools.args import PositiveFiniteFloat, Seed, run
from omg.tools.export import OutputFormat
from omg.tools.generate import run_generation


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
    format: OutputFormat | None = None,
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
        to_rig: write the transfer onto this quadruped rig: a BVH file's (its hierarchy, names, channels, unit),
            a skinned glTF character (.glb, .gltf) or an FBX character (.fbx: pip install 'omg[fbx]')
        to_rig_joint_map: the --to_rig rig's joint map (a registered name or a YAML file; default: detected;
            --joint_map is the source's)
        format: bvh, glb (glTF 2.0 binary: joint nodes, a skin and the animation; onto a character, the
            character with the animation added) or fbx (onto an FBX character, the character with the
            animation added); default: glb with a .glb/.gltf --to_rig, fbx with an .fbx one, else bvh
        out: output folder (created; files in it are overwritten)
        command: the command line, recorded in transfer.json

    Returns:
        The settings written to transfer.json.
    """
    from omg.export import output_format
    from omg.lit.habit import HabitVQModule

    format = output_format(format, to_rig)
    settings = run_generation(
        ckpt, prompts=[], animal=to, from_motion=Path(source), from_motion_joint_map=joint_map,
        prior_ckpt=prior_ckpt, seed=seed, options={"species_file": species_file, "temperature": temperature,
                                                   "quantizer": quantizer},
        preview=preview, to_rig=to_rig, joint_map=to_rig_joint_map, format=format, device="cpu", out=out,
        command=command, expect=HabitVQModule, names=["transfer"], settings_file="transfer.json",
        extra_files=("source.*.npy",),
        extra_settings={"source": str(source), format: str(Path(out) / f"transfer.{format}")})
    via = (f" via the nearest known category {settings['category']} (text distance {settings['distance']:.3f})"
           if settings["retrieved"] else "")
    print(f"transferred {Path(source).name} ({settings['frames']} frames at {settings['fps']:g} fps) to {to}{via}: "
          f"{out}")
    return settings


def main(argv: list[str]) -> None:
    run(transfer, argv, "omg transfer", positional="source", nargs=None)
