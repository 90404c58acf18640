"""The ``animalml3d`` source: OmniMotionGPT's AnimalML3D release (Yang et al. 2024) on smal35.

Expected layout under ``--input`` (the unzipped ``data/*.zip`` of USRC-SEA/OmniMotionGPT)::

    animals_maa_motions/<animal>_<action>.npy        (T, 36, 6) MAA motion, see below
    motion_captions/<animal>_<action>/screenshots.txt captions, one per line (``caption#...``);
                                                     ``animals/`` is accepted instead of
                                                     ``motion_captions/`` (the training code's path)
    animals_maa_offsets/<animal>/offset.pkl          (35, 3) pickled float array: the bone offsets
    animals_maa_offsets/<animal>/{mean,std}.npy      per-animal statistics (not used, see below)

The animal identity is the file name up to the first ``_`` (as in OmniMotionGPT): it picks the
offsets and the split. The clip's ``category`` is the identity's species, the word its captions
use ("bear3EP" -> "bear", "canieLTT" -> "wolf": ``omg/text/animals.yaml``, every identity of the
release; option ``species``, a mapping identity -> word, adds or overrides identities), so that
training, ``find_animal``, the OOD prompts and ``omg generate --animal`` speak of "a bear";
``labels`` keep ``identity``, ``species`` and ``action``. A clip of an identity without a species
is skipped and counted. Clips without captions are skipped and counted, as the released
training code drops them; so are clips outside ``min_frames <= T <= max_frames`` (default
10 and 196, the paper's AnimalML3D filter). Motion is taken to be at 20 fps (OmniMotionGPT
trains it beside HumanML3D's 20 fps clips).

Split (option ``split``: ``train``, ``test`` or ``all``, default ``all``): by identity, 23
train / 13 test in the paper. The official identity lists (``smal_animal_names_v1_train`` in
OmniMotionGPT's private ``ylib``) are not public, so the test identities are an explicit
option, ``test_animals`` (comma-separated names or a YAML list); without it, a documented
deterministic default: the identities present, ranked by the SHA-1 of their name, the first
``round(n * 13 / 36)`` are test (13 of the 36 in the full release).

The MAA file's rows 0..34 are 6D rotations (first two columns of the matrix) in HumanML3D's
chain convention: the rotation at joint b turns bone parent(b) -> b, composed along its
kinematic chain starting from the root rotation (row 0) at every chain start; row 35 is the
root position and 3 zeros. The importer decodes them by that chain FK with the animal's
offsets (OmniMotionGPT's ``convert_maa_motion_to_positions``) and re-solves per-joint local
rotations in omg's convention (a joint's rotation turns its children's offsets; joints
with several children take the best rigid fit), so omg's ``maa`` features are re-encoded,
not copied, and the per-animal mean/std of the chain-convention files do not apply.
"""

from __future__ import annotations

import hashlib
import io
import pickle
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from omg.errors import UsageError
from omg.files import MOTION_MAX_BYTES, read_array, read_file, read_text
from omg.kinematics import kabsch
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.rotations import matrix_to_quat, sixd_to_matrix
from omg.skeleton import SMAL35, Skeleton
from omg.text.omgpt import species_of

FPS = 20.0
NUM_TEST_OF_36 = 13  # the paper's 23 train / 13 test identities


class _ArrayUnpickler(pickle.Unpickler):
    """offset.pkl holds one numpy array; refuse anything else a pickle could run."""

    ALLOWED = {
        ("numpy", "ndarray"), ("numpy", "dtype"),
        ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    }  # fmt: skip

    def find_class(self, module: str, name: str):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not a numpy array part")


def load_offsets(path: Path) -> np.ndarray:
    """(35, 3) offsets from ``offset.pkl``; ValueError names the file and reason."""
    if not path.exists():
        raise ValueError(f"animalml3d missing offsets: {path}")
    try:
        data = read_file(path, "", MOTION_MAX_BYTES)
        offsets = np.asarray(_ArrayUnpickler(io.BytesIO(data)).load(), dtype=np.float64)
    except Exception as e:  # noqa: BLE001 - any unreadable file (a FIFO, a huge file too) is one counted skip
        raise ValueError(f"animalml3d unreadable offsets: {path} ({type(e).__name__}: {e})") from None
    if offsets.shape != (35, 3) or not np.isfinite(offsets).all():
        raise ValueError(f"animalml3d bad offsets: {path} is {offsets.shape}, expected finite (35, 3)")
    return offsets


def chain_fk(sixd: np.ndarray, root: np.ndarray, offsets: np.ndarray, chains) -> tuple[np.ndarray, np.ndarray]:
    """OmniMotionGPT/HumanML3D chain FK.

    (T, J, 6) rotations, (T, 3) root, (J, 3) offsets -> positions (T, J, 3) and each bone's
    global rotation (T, J, 3, 3) (row b turns offsets[b]; row 0 is the root rotation).
    """
    M = sixd_to_matrix(torch.from_numpy(sixd)).numpy()  # (T, J, 3, 3)
    T, J = sixd.shape[:2]
    positions = np.zeros((T, J, 3))
    positions[:, 0] = root
    bone_rot = np.zeros((T, J, 3, 3))
    bone_rot[:, 0] = M[:, 0]
    for chain in chains:
        R = M[:, 0]
        for a, b in zip(chain[:-1], chain[1:]):
            R = R @ M[:, b]
            bone_rot[:, b] = R
            positions[:, b] = positions[:, a] + R @ offsets[b]
    return positions, bone_rot


def local_rotations(skeleton: Skeleton, bone_rot: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Per-bone global rotations (T, J, 3, 3) -> omg local quaternions (T, J, 4).

    In omg a joint's rotation turns all its children's offsets: one child gives it that
    bone's rotation exactly; several children give the rotation that best maps their rest
    offsets onto their bones (Kabsch); leaves keep their parent's rotation.
    """
    T, J = bone_rot.shape[:2]
    glob = np.zeros((T, J, 3, 3))
    for a in range(J):
        kids = skeleton.children(a)
        if not kids:
            glob[:, a] = glob[:, skeleton.parents[a]]
        elif len(kids) == 1:
            glob[:, a] = bone_rot[:, kids[0]]
        else:
            rest = offsets[kids]  # (K, 3)
            bones = np.einsum("tkij,kj->tki", bone_rot[:, kids], rest)  # (T, K, 3)
            glob[:, a] = kabsch(torch.from_numpy(rest), torch.from_numpy(bones)).numpy()
    local = glob.copy()
    for a in range(1, J):
        local[:, a] = np.swapaxes(glob[:, skeleton.parents[a]], -1, -2) @ glob[:, a]
    return matrix_to_quat(torch.from_numpy(local)).numpy()


def default_test_animals(animals: list[str]) -> set[str]:
    """Deterministic stand-in for the unpublished identity split: 13/36 of the identities,
    the ones with the smallest SHA-1 of their name."""
    ranked = sorted(animals, key=lambda a: hashlib.sha1(a.encode()).hexdigest())
    return set(ranked[: round(len(ranked) * NUM_TEST_OF_36 / 36)])


def _captions(root: Path, name: str) -> list[str]:
    for folder in ("motion_captions", "animals"):
        path = root / folder / name / "screenshots.txt"
        if path.exists():
            try:
                lines = read_text(path, "").splitlines()
            except UsageError as e:  # a FIFO, a huge or non-UTF-8 file: a counted skip, not the build's end
                raise ValueError(f"animalml3d unreadable captions: {path} ({type(e).__name__}: {e})") from None
            captions = [line.split("#")[0].strip() for line in lines if line.split("#")[0].strip()]
            if not captions:
                raise ValueError(f"animalml3d empty captions: {path}")
            return captions
    raise ValueError(f"animalml3d missing captions: {root / 'motion_captions' / name / 'screenshots.txt'}")


def _read_clip(root: Path, path: Path, skeleton: Skeleton, min_frames: int, max_frames: int,
               species: dict[str, str]) -> Clip:
    name = path.stem
    animal, _, action = name.partition("_")
    if not (word := species.get(animal) or species_of(animal)):
        raise ValueError(f"animalml3d unknown identity: {path} ({animal!r} has no species word; give "
                         f"--option.species '{{{animal}: WORD}}')")
    try:
        motion = read_array(path, "").astype(np.float64)
    except Exception as e:  # noqa: BLE001 - a FIFO or a huge file too: one counted skip
        raise ValueError(f"animalml3d unreadable motion: {path} ({type(e).__name__}: {e})") from None
    J = skeleton.num_joints
    if motion.ndim == 2 and motion.shape[1] == (J + 1) * 6:
        motion = motion.reshape(len(motion), J + 1, 6)
    if motion.ndim != 3 or motion.shape[1:] != (J + 1, 6):
        raise ValueError(f"animalml3d wrong array shape: {path} is {motion.shape}, expected (T, {J + 1}, 6)")
    if not np.isfinite(motion).all():
        raise ValueError(f"animalml3d NaN or inf in motion: {path}")
    if len(motion) < min_frames or (max_frames and len(motion) > max_frames):
        raise ValueError(f"animalml3d length outside [{min_frames}, {max_frames or 'inf'}] frames: "
                         f"{path} has {len(motion)}")
    texts = _captions(root, name)
    offsets = load_offsets(root / "animals_maa_offsets" / animal / "offset.pkl")
    positions, bone_rot = chain_fk(motion[:, :J], motion[:, J, :3], offsets, skeleton.chains)
    return Clip(
        id=name,
        skeleton=skeleton,
        fps=FPS,
        positions=positions.astype(np.float32),
        rotations=local_rotations(skeleton, bone_rot, offsets).astype(np.float32),
        offsets=offsets.astype(np.float32),
        texts=texts,
        labels={"identity": animal, "species": word, "action": action},
        category=word,
        source="animalml3d",
    )


@DATA_SOURCES.register("animalml3d")
def animalml3d_source(
    input: str | None,
    skeleton: Skeleton,
    fps: float,
    split: str = "all",
    test_animals: str | list[str] | None = None,
    min_frames: int = 10,
    max_frames: int = 196,
    species: dict[str, str] | None = None,
) -> Iterator[Clip | Exception]:
    """Captioned SMAL-35 animal clips of AnimalML3D; see the module docstring."""
    motions = Path(input or "") / "animals_maa_motions"
    if not input or not motions.is_dir():
        raise UsageError("animalml3d: --input must be the AnimalML3D folder holding animals_maa_motions/, "
                         f"got {input!r}")
    if list(skeleton.parents) != list(SMAL35.parents):
        raise UsageError(f"animalml3d motion is on smal35, not {skeleton.name!r}; use --skeleton smal35")
    if abs(fps - FPS) > 1e-6:
        raise UsageError(f"animalml3d motion is at {FPS:g} fps; use --fps {FPS:g}")
    species = species or {}
    if not isinstance(species, dict) or not all(isinstance(w, str) and w.strip() for w in species.values()):
        raise UsageError(f"animalml3d: --option.species must map identities to species words, got {species!r}")
    species = {str(k): v.strip() for k, v in species.items()}
    if split not in ("train", "test", "all"):
        raise UsageError(f"animalml3d: --option.split {split!r}; choose train, test or all")
    paths = sorted(motions.glob("*.npy"))
    animals = sorted({p.stem.split("_")[0] for p in paths})
    if test_animals is None:
        test = default_test_animals(animals)
    else:
        test = set(test_animals.split(",") if isinstance(test_animals, str) else map(str, test_animals))
        if unknown := sorted(test - set(animals)):
            raise UsageError(f"animalml3d: test_animals {unknown} are not in {motions}; "
                             f"identities: {', '.join(animals)}")
    keep = {"all": set(animals), "test": test, "train": set(animals) - test}[split]

    def items() -> Iterator[Clip | Exception]:
        for path in paths:
            if path.stem.split("_")[0] in keep:
                try:
                    yield _read_clip(Path(input), path, skeleton, min_frames, max_frames, species)
                except ValueError as e:
                    yield e

    return items()
