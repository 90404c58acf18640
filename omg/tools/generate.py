"""``omg generate``: sample motions from a checkpoint and write them with their settings.

Per sample it writes ``sample_NNN.features.npy`` (T, D) in the checkpoint's representation
(HumanML3D-compatible for humanml3d263), ``sample_NNN.joints.npy`` (T, J, 3) joint positions
in metres, Y up, and ``sample_NNN.bvh`` (rotations solved by IK on the model's skeleton);
``preview.gif`` shows the first motions side by side with their captions, and
``generation.json`` records every setting, so that a result can be reproduced exactly.
"""

from __future__ import annotations

import math
import sys
import time
import unicodedata
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal, TextIO

import torch

from omg.errors import UsageError
from omg.export import output_format
from omg.files import check_output_dir, read_text
from omg.generation.progress import Progress, ProgressClock
from omg.generation.protocol import MAX_SECONDS, GenerationRequest, check_request, parse_options
from omg.generation.write import MAX_PREVIEW, check_finite_motions, output_files, write_generation
from omg.registry import SAMPLERS
from omg.retarget import read_rig
from omg.tools.args import ClosedUnitInterval, FiniteFloat, PositiveInt, Seed, number_type, repeated, run
from omg.tools.export import OutputFormat

AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}
Seconds = number_type("Seconds", float, [(">", 0.0), ("<=", MAX_SECONDS)],
                      f"a number of seconds in (0, {MAX_SECONDS:g}]")


def generate(
    prompts: list[str] | None = None,
    *,
    ckpt: Path,
    prompts_file: Path | None = None,
    unconditional: bool = False,
    num_samples: PositiveInt = 4,
    length: Seconds | None = None,
    timeline: Path | None = None,
    steps: PositiveInt | None = None,
    sampler: str | None = None,
    guidance: FiniteFloat | None = None,
    seed: Seed = 0,
    batch_size: PositiveInt = 32,
    ema: bool = True,
    preview: bool = True,
    preview_count: PositiveInt = MAX_PREVIEW,
    progress: bool = True,
    clean_contacts: bool = False,
    stance_root: ClosedUnitInterval | None = None,
    option: list[str] | None = None,
    to_rig: Path | None = None,
    joint_map: str | None = None,
    format: OutputFormat | None = None,
    device: str | None = None,
    autocast: Literal["bf16", "fp16"] | None = None,
    compile: bool = False,
    animal: str | None = None,
    from_motion: Path | None = None,
    from_motion_joint_map: str | None = None,
    human_ckpt: Path | None = None,
    prior_ckpt: Path | None = None,
    constraints: Path | None = None,
    out: Path = Path("out/generate"),
    command: str = "",
) -> dict:
    """Generate motions from a trained checkpoint of any family.

    Writes per motion its features, joint positions and a BVH file, a preview.gif of the first
    motions and generation.json with every setting (the command reproduces the result). What a
    checkpoint generates from (prompts, nothing, a source motion, a species) is its generation
    card's (``omg.generation``); an option it does not take is one line before sampling.

    Args:
        prompts: text prompts (needs a text-conditioned checkpoint)
        ckpt: a .ckpt file, a DeepSpeed checkpoint directory or a .safetensors file
        prompts_file: a UTF-8 text file with one prompt per line
        unconditional: sample the pretrained motion prior without text
        num_samples: motions per prompt (or in total when unconditional or with --timeline)
        length: seconds per motion (default 6, or the --timeline's end)
        timeline: a JSON prompt timeline and body-part composition, instead of prompts (docs/guide/timelines.md):
            [{"start": 0, "end": 3, "text": ...}, ...] or {"timeline": [...], "parts": [{"parts": ["left_arm"],
            "text": ...}, ...]}; text-conditioned OMG checkpoints (their card lists timeline)
        steps: sampling steps (at most the checkpoint's diffusion steps; default OMG's 200 DDIM steps)
        sampler: a registered sampler: ddim (OMG's, the default), dpmpp (DPM-Solver++(2M): ~20 steps), euler
        guidance: classifier-free guidance scale s (default: the checkpoint's, OMG: 4.5)
        seed: random seed
        batch_size: motions sampled at once
        ema: use the EMA of the weights (--no_ema: the trained weights)
        preview: write preview.gif
        preview_count: motions shown side by side in preview.gif
        progress: show sampling progress on stderr: in a terminal a live line (the motions in the sampler, its
            step, the time elapsed and left), otherwise one line per batch of motions made (--no_progress: none)
        clean_contacts: pin planted feet in the BVH files (removes foot skating)
        stance_root: OMG checkpoints of humanml3d263 motion: step the root by the stance foot at every
            sampling step, this much in [0, 1] (default: the checkpoint's; removes foot sliding while sampling)
        option: a family option of the checkpoint's generation card as KEY=VALUE, repeatable (e.g. habit
            transfer's temperature=0.8, quantizer=nearest, species_file=FILE; OMG's stance_root=0.5)
        to_rig: write each motion onto this rig: a BVH file's (its hierarchy, names, channels, unit, rest pose),
            a skinned glTF character (.glb, .gltf: the character, its mesh and materials kept), or an FBX
            character (.fbx, read and written by Blender: pip install 'omg[fbx]')
        joint_map: the rig's joint map for --to_rig (a registered name or a YAML file; default: detected)
        format: bvh, glb (glTF 2.0 binary: joint nodes, a skin and the animation; onto a character, the
            character with the animation added) or fbx (onto an FBX character, the character with the
            animation added); default: glb with a .glb/.gltf --to_rig, fbx with an .fbx one, else bvh
        device: cpu, cuda, cuda:N or mps (default: cuda when available, else cpu)
        autocast: run the network under autocast in this dtype (bf16 on recent GPUs; the sampler's
            update stays in float32)
        compile: run the network through torch.compile (a one-off compilation, then faster steps)
        animal: checkpoints that take a species (OmniMotionGPT, habit transfer): the animal; it wins over the
            animal the prompt names, and the prompt is made about it (default: the one the prompt names)
        from_motion: checkpoints that take a source motion: the motion file (OmniMotionGPT: the human motion to
            turn into the animal's, a BVH, ASF/AMC or DeepMimic file retargeted to smpl22, a .joints.npy
            (T, 22, 3), or a features .npy in smpl22 maa or humanml3d263; one motion per prompt; habit transfer:
            the quadruped motion to move onto --animal, a BVH, DeepMimic or .npy file)
        from_motion_joint_map: the --from_motion rig's joint map (a registered name or a YAML file; default:
            detected)
        human_ckpt: checkpoints whose source motion a second model may make (OmniMotionGPT): a text-to-motion
            checkpoint (OMG ControlNet) that generates the human motion from the prompt made about "a person"
            (without either, the checkpoint's own human source)
        prior_ckpt: habit checkpoints of the kl_then_flows order: the HabitPriorModule checkpoint whose flows
            draw the habit latent (without it, the checkpoint's own flows or the mean of the target's posterior)
        constraints: a JSON file of spatial constraints (keyframes, joint targets, root waypoints and paths, facing,
            foot contacts; docs/guide/control.md) the motions are steered to meet, for checkpoints whose card takes
            them (OMG); one not met is written with a warning stating the error reached
        out: output folder (created; files in it are overwritten)
        command: the command line, recorded in generation.json

    Returns:
        The settings written to generation.json.
    """
    from omg.generation.timeline import read_timeline

    spans = read_timeline(timeline, check_plain_text) if timeline is not None else None
    if length is None:
        length = spans.end if spans is not None and spans.end is not None else 6.0
    settings = run_generation(
        ckpt, prompts=read_prompts(prompts or [], prompts_file), unconditional=unconditional, timeline=spans,
        num_samples=num_samples, length=length, steps=steps, sampler=sampler, guidance=guidance, seed=seed,
        batch_size=batch_size, ema=ema, preview=preview, preview_count=preview_count, progress=progress,
        clean_contacts=clean_contacts,
        options=([f"stance_root={stance_root}"] if stance_root is not None else []) + list(option or []),
        to_rig=to_rig, joint_map=joint_map, format=format, device=device, autocast=autocast, compile=compile,
        animal=animal, from_motion=from_motion, from_motion_joint_map=from_motion_joint_map, human_ckpt=human_ckpt,
        prior_ckpt=prior_ckpt, constraints=constraints, out=out, command=command)
    frames, fps = settings["frames"], settings["fps"]
    print(f"wrote {len(settings['samples'])} motions of {frames} frames ({frames / fps:g} s at {fps:g} fps) to {out}")
    return settings


def run_generation(ckpt: Path, *, prompts: list[str], out: Path, command: str, unconditional: bool = False,
                   timeline: Any = None,
                   num_samples: int = 1, length: float | None = None, steps: int | None = None,
                   sampler: str | None = None, guidance: float | None = None, seed: int = 0, batch_size: int = 32,
                   ema: bool = True, preview: bool = True, preview_count: int = MAX_PREVIEW, progress: bool = False,
                   clean_contacts: bool = False, options: list[str] | dict[str, Any] = (), to_rig: Path | None = None,
                   joint_map: str | None = None, format: str | None = None, device: str | None = None,
                   autocast: str | None = None, compile: bool = False, animal: str | None = None,
                   from_motion: Path | None = None, from_motion_joint_map: str | None = None,
                   human_ckpt: Path | None = None, prior_ckpt: Path | None = None, constraints: Path | None = None,
                   expect: type | None = None,
                   names: list[str] | None = None, settings_file: str = "generation.json",
                   extra_files: tuple[str, ...] = (), extra_settings: dict[str, Any] | None = None) -> dict:
    """``omg generate`` and its aliases (``omg transfer``): every input checked before anything is loaded or
    written, the checkpoint's generator (``omg.generation.registry``) asked for the motions, the one writer
    (``omg.generation.write``) writing them. ``options``: ``--option KEY=VALUE`` pairs, or the family options
    already typed (an alias's own flags); ``length`` None: the source motion's (a transfer); ``names``,
    ``settings_file``, ``extra_files`` and ``extra_settings``: an alias's file names and what its settings add;
    ``timeline``: a read ``omg.generation.timeline.TimelineFile``, instead of prompts; ``progress``: a
    ``ProgressLine`` on stderr while the motions are made."""
    from omg.generation.registry import generator_for
    from omg.lit.checkpoint import load_module
    from omg.lit.pretrain import PretrainModule

    if animal is not None:  # a description of an animal goes to the text encoder as a prompt does
        check_plain_text(animal, "--animal")
    if timeline is not None and (prompts or unconditional):
        raise UsageError(f"give prompts, --timeline (whose segments carry their texts) or --unconditional, not "
                         f"{'prompts' if prompts else '--unconditional'} and --timeline")
    if unconditional == (bool(prompts) or timeline is not None) and from_motion is None:
        raise UsageError("give prompts (or --prompts_file) for text-to-motion, or --unconditional to sample the "
                         "motion prior")
    if sampler is not None:
        SAMPLERS.get(sampler)  # an unknown name is one line before anything is loaded
    if joint_map is not None and to_rig is None:
        raise UsageError("--joint_map names the map of the --to_rig rig; give --to_rig RIG (.bvh, .glb, .gltf, "
                         ".fbx) with it")
    format = output_format(format, to_rig)
    if to_rig is not None and Path(to_rig).suffix.lower() == ".fbx":  # no Blender: one line before the model loads
        from omg.io.fbx import check_file

        check_file(to_rig)
    if from_motion is not None and human_ckpt is not None:
        raise UsageError("give --from_motion (a human motion file) or --human_ckpt (a ControlNet checkpoint), not both")
    if from_motion_joint_map is not None and from_motion is None:
        raise UsageError("--from_motion_joint_map names the map of the --from_motion file; give --from_motion with it")
    device = resolve_device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    # every input is checked before anything is written; a folder where a motion file goes would fail the write
    stems = names[0] if names and len(names) == 1 else "sample_*"
    out = check_output_dir(out, files=(*output_files(stems, format, settings_file, preview), *extra_files))
    module = load_module(ckpt, default_class=PretrainModule, use_ema=ema, expect=expect)
    generator = generator_for(module, ckpt)
    what = f"{ckpt} ({type(module).__name__})"
    if prior_ckpt is not None:
        if not generator.takes_prior:  # one line before the prior is read
            raise UsageError(f"--prior_ckpt: {what} takes no prior checkpoint")
        generator.with_prior(load_prior(prior_ckpt, ckpt, module))
    card = generator.generation_card()
    typed = dict(options) if isinstance(options, dict) else parse_options(generator, list(options), what)
    if length is None and not card.source_fixes_length:
        raise UsageError(f"{what} needs --length: its motions' length is not its source motion's")
    # a transfer's frames are its source motion's (``source_fixes_length``): the card's least stands in until read
    frames = round(length * card.fps) if length is not None else card.min_frames
    request = GenerationRequest(prompts=prompts or None, frames=frames, num_samples=num_samples,
                                seed=seed, steps=steps, sampler=sampler, guidance=guidance, species=animal,
                                batch_size=batch_size, autocast=AUTOCAST.get(autocast), compile=compile,
                                options=typed, timeline=timeline)
    if human_ckpt is not None:
        request.source_module = generator_for(load_module(human_ckpt), human_ckpt).to(device)
    request.source = from_motion  # read once the card says the model takes it
    check_request(card, request, what)
    given = None
    if constraints is not None:  # read and resolved before anything is sampled or written
        from omg.generation.control import read_constraints

        request.control, given = read_constraints(constraints, card, frames)
    if from_motion is not None:
        request.source = generator.read_source(from_motion, from_motion_joint_map)
    rig = read_rig(to_rig, card.skeleton, joint_map) if to_rig is not None else None  # checked before sampling
    generator = generator.to(device)
    request.progress = ProgressLine(sys.stderr) if progress else None
    try:
        motions = generator.generate(request)
    finally:  # an error or Ctrl-C starts on a line of its own
        if request.progress is not None:
            request.progress.close()
    check_finite_motions(motions, ckpt, f" or --guidance {guidance:g} too large" if prompts and guidance is not None
                         else "")
    for i, motion in enumerate(motions):  # a constraint that cannot be met is generated, never silently
        for name, error in motion.record.get("control_unmet", {}).items():
            print(f"omg: warning: motion {i}: {name} not met: {100 * error:.1f} cm from its target at worst",
                  file=sys.stderr)
    settings = {"command": command, "ckpt": str(ckpt), "module": type(module).__name__, "family": card.family,
                "prompts": prompts, "num_samples": num_samples, "length_s": length, "frames": request.frames,
                "fps": card.fps, "seed": seed, "ema": ema, "autocast": autocast, "compile": compile,
                "from_motion": None if from_motion is None else str(from_motion),
                "human_ckpt": None if human_ckpt is None else str(human_ckpt),
                "prior_ckpt": None if prior_ckpt is None else str(prior_ckpt), "clean_contacts": clean_contacts,
                **({} if constraints is None else {"constraints_file": str(constraints), "constraints": given}),
                "to_rig": None if to_rig is None else str(to_rig), "joint_map": joint_map, "format": format,
                **generator.generation_settings(request),
                "representation": card.representation, "skeleton": card.skeleton, **(extra_settings or {})}
    write_generation(out, motions, card, settings, names=names, settings_file=settings_file, rig=rig,
                     joint_map=joint_map, format=format, clean_contacts=clean_contacts, preview=preview,
                     preview_count=preview_count)
    return settings


class ProgressLine:
    """``omg generate``'s progress on ``stream`` (stderr: stdout keeps its one line of results), a
    ``ProgressReport``: in a terminal one line redrawn in place (the motions in the sampler, its step, the time
    elapsed and about how long is left, from the seconds per step measured: ``ProgressClock``); in a log file or a
    pipe, which would receive a redrawn line only at the end, one line per batch of motions made with the same
    facts."""

    redraw_s = 0.1  # the live line is drawn at most this often, and at each batch's start and end

    def __init__(self, stream: TextIO, live: bool | None = None, clock: Callable[[], float] = time.perf_counter):
        self.stream = stream
        self.live = stream.isatty() if live is None else live
        self.clock = ProgressClock(clock=clock)
        self._drawn = -math.inf  # when the live line was last drawn
        self._width = 0  # its length then: a shorter line covers it with spaces

    def __call__(self, progress: Progress) -> None:
        self.clock(progress)
        if self.live:
            now = self.clock.clock()
            if progress.finished or progress.step == 0 or now - self._drawn >= self.redraw_s:
                text = self.text(progress)
                self.stream.write("\r" + text.ljust(self._width))
                self.stream.flush()
                self._drawn, self._width = now, len(text)
        elif progress.finished:
            print(self.text(progress), file=self.stream, flush=True)

    def text(self, p: Progress) -> str:
        """``motions 1-4 of 8: step 37 of 200, 3s elapsed, about 40s left`` while a batch samples,
        ``motions 1-4 of 8 made in 200 steps, 12s elapsed, about 12s left`` when it is made."""
        # fit's formatting; imported here, where the model (and lightning) is loaded, not by every omg generate
        from omg.callbacks.progress import duration

        if p.finished:
            head = f"{p.motions} made" + (f" in {p.steps} steps" if p.steps else "")
        else:
            head = p.motions + (f": step {p.step} of {p.steps}" if p.steps else "")
        parts = [head, f"{duration(self.clock.elapsed())} elapsed"]
        left = self.clock.time_left()
        if p.done < p.total and left is not None:
            parts.append(f"about {duration(left)} left")
        return ", ".join(parts)

    def close(self) -> None:
        """Ends the live line, so that what follows starts on a line of its own."""
        if self.live and self._drawn > -math.inf:
            self.stream.write("\n")
            self.stream.flush()


def load_prior(prior_ckpt: Path, ckpt: Path, module) -> Any:
    """The ``--prior_ckpt`` habit prior, fitted for the categories ``module`` (``--ckpt``, a habit checkpoint: its
    generator ``takes_prior``) knows."""
    from omg.lit.checkpoint import load_module
    from omg.lit.habit import HabitPriorModule

    prior = load_module(prior_ckpt, default_class=HabitPriorModule, expect=HabitPriorModule)
    if prior.categories != module.categories:
        raise UsageError(f"--prior_ckpt {prior_ckpt} was fitted for categories {prior.categories}, --ckpt {ckpt} "
                         f"knows {module.categories}: fit the prior on this VQ-VAE")
    return prior


def _control_character(text: str) -> str | None:
    """The first character of ``text`` no text encoder should see: a control character but tab (C0, DEL, C1), or a
    surrogate, which UTF-8 cannot encode (an undecodable byte of the command line, or JSON's lone ``\\ud800``)."""
    return next((c for c in text if c != "\t" and unicodedata.category(c) in ("Cc", "Cs")), None)


def check_plain_text(text: str, what: str) -> str:
    """``text`` when it is plain text (``_control_character``); one line naming ``what`` otherwise. The one check of
    text given to a model, for ``omg generate`` and ``omg serve`` alike."""
    if (c := _control_character(text)) is not None:
        kind = "the control character" if unicodedata.category(c) == "Cc" else "a lone surrogate or undecodable byte"
        raise UsageError(f"{what} holds {kind} {c!r}, which is not text; give plain text")
    return text


def read_prompts(prompts: list[str], prompts_file: str | Path | None = None) -> list[str]:
    """The prompts given and those of ``prompts_file`` (one per line), checked."""
    prompts = list(prompts)
    for i, prompt in enumerate(prompts):
        check_plain_text(prompt, f"prompt {i + 1}")
    if prompts_file:
        lines = read_text(prompts_file, "--prompts_file").splitlines()
        for number, line in enumerate(lines, start=1):
            if (c := _control_character(line)) is not None:
                raise UsageError(f"--prompts_file {prompts_file}: line {number} holds the control character {c!r}; "
                                 "expected a text file with one prompt per line")
        prompts += [line.strip() for line in lines if line.strip()]
    if empty := [i for i, p in enumerate(prompts) if not p.strip()]:
        raise UsageError(f"prompt {empty[0] + 1} is empty; give a sentence such as \"a person walks forward\"")
    return prompts


def resolve_device(name: str) -> torch.device:
    """``--device`` as a torch device that exists on this machine."""
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda", "mps"):
        raise UsageError(f"--device {name!r}: not a device; use cpu, cuda, cuda:N or mps")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise UsageError(f"--device {name}: no CUDA GPU is available here; use --device cpu")
        if device.index is not None and device.index >= count:
            raise UsageError(f"--device {name}: this machine has {count} CUDA GPU{'s' if count > 1 else ''} "
                             f"(cuda:0{f' to cuda:{count - 1}' if count > 1 else ''})")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise UsageError(f"--device {name}: MPS (Apple GPU) is not available here; use --device cpu")
    return device


def main(argv: list[str]) -> None:
    run(generate, repeated(argv, "--option"), "omg generate", positional="prompts")
