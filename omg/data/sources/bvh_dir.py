"""The ``bvh-dir`` source: a folder of motion files retargeted onto the target skeleton.

``input`` is a folder. With a ``manifest.json`` in it (``{"clips": [{"id", "path", "format",
"domain", "texts", "labels", "skeleton_file", "fps", ...}]}``, paths relative to the folder;
format ``bvh``, ``deepmimic_json`` or ``asf/amc``, where ``skeleton_file`` is the DeepMimic
character or the ASF and ``fps`` the AMC rate) the clips are exactly its entries.

Without one, every motion file below the folder is a clip: ``*.bvh``, ``*.amc`` (with
``NN.asf`` beside ``NN_MM.amc``) and DeepMimic motions (``*.txt`` / ``*.json`` holding a
JSON object with ``"Frames"``; character files and other text files are passed over). The
id is the path relative to the folder without its suffix. Captions come from an optional
sidecar ``<stem>.captions.txt`` beside the file, one caption per line (the ``.captions.txt``
ending keeps sidecars apart from DeepMimic's own ``.txt`` motions); clips without one are
imported unlabeled.

Domains: a clip's domain is its manifest ``domain``, or else the category of the joint map
that fits its rig (``human`` for maps onto smpl22, the species, e.g. ``dog``, for smal35).
smpl22 imports human clips only, smal35 every other domain (quadrupeds); clips of other
domains are passed over silently. The ``domain`` option overrides this: a domain name, a
comma-separated list, or ``all``.

Options: ``joint_map`` (a built-in map name or a YAML file, see ``omg.retarget``; default:
detected per clip), ``height`` (metres, rescales every clip, see ``omg.retarget.retarget``),
``domain``. A clip that fails becomes a yielded error, counted in the build summary by
category (``bad motion file``: truncated or garbled files, unknown BVH channels, zero
frames, NaN values, a FIFO or device named like a motion; ``unmappable rig``; ``duplicate clip id``;
``missing file``; ``bad captions file``: a sidecar that is no regular file or is too large), with
the file and the reason in its message.
"""

from __future__ import annotations

import json
from pathlib import Path

from omg.data.shards import LazyItem
from omg.errors import UsageError
from omg.files import MANIFEST_MAX_BYTES, TEXT_MAX_BYTES, read_file
from omg.motion import Clip
from omg.registry import DATA_SOURCES
from omg.skeleton import Skeleton

SIDECAR = ".captions.txt"


class SkippedClip(UsageError):
    """One clip of the folder that cannot be imported: "<category>: <file>: <reason>"."""


def _captions(path: Path) -> list[str]:
    sidecar = path.with_name(path.stem + SIDECAR)
    if not sidecar.exists():
        return []
    try:
        text = read_file(sidecar, "", TEXT_MAX_BYTES).decode("utf-8", errors="replace")
    except UsageError as e:  # a FIFO (which would block the scan) or a huge file
        raise SkippedClip(f"bad captions file: {e}") from None
    return [line.strip() for line in text.splitlines() if line.strip()]


def _scan(folder: Path) -> list[dict | SkippedClip]:
    """Manifest-like entries for the motion files below ``folder``; a clip whose captions sidecar
    cannot be read is its ``SkippedClip`` (counted, the others still imported)."""
    from omg.io.deepmimic import is_deepmimic_motion

    entries: list[dict | SkippedClip] = []
    for path in sorted(p for p in folder.rglob("*") if not p.is_dir()):  # a FIFO .bvh too: a counted skip
        suffix = path.suffix.lower()
        if path.name.endswith(SIDECAR):
            continue
        if suffix in (".bvh", ".amc") or (suffix in (".txt", ".json") and is_deepmimic_motion(path)):
            rel = path.relative_to(folder)
            try:
                entries.append({"id": rel.with_suffix("").as_posix(), "path": rel.as_posix(), "texts": _captions(path)})
            except SkippedClip as e:
                entries.append(e)
    return entries


def _wanted(domain: str | None, skeleton: Skeleton, only: str | list | None) -> bool:
    if only is not None:
        names = only if isinstance(only, list) else [d.strip() for d in str(only).split(",")]
        return "all" in names or domain in names
    if skeleton.name == "smpl22":
        return domain == "human"
    if skeleton.name == "smal35":
        return domain != "human"
    return True


def _reader_options(entry: dict, folder: Path) -> dict:
    fmt = str(entry.get("format", "")).lower()
    extra = entry.get("skeleton_file")
    if fmt == "deepmimic_json" and extra:
        return {"character": folder / extra}
    if fmt in ("asf/amc", "amc"):
        options = {"fps": float(entry["fps"])} if entry.get("fps") else {}
        return options | ({"asf": folder / extra} if extra else {})
    return {}


def _import(entry: dict, folder: Path, skeleton: Skeleton, fps: float, joint_map, height, only) -> Clip | None:
    from omg.io.read import read_motion
    from omg.retarget import detect_joint_map, get_joint_map, retarget

    path = folder / entry["path"]
    if not path.exists():  # a FIFO or folder is no missing file: read_motion refuses it, a bad motion file
        raise SkippedClip(f"missing file: {path}: listed in the manifest but not found")
    try:
        motion = read_motion(path, **_reader_options(entry, folder))
    except (UsageError, OSError) as e:
        raise SkippedClip(f"bad motion file: {e}") from None
    domain = entry.get("domain")
    if domain is None:  # no manifest: the rig tells
        found = get_joint_map(joint_map) if joint_map is not None else detect_joint_map(motion)
        domain = found.category if found is not None else None
    if domain is not None and not _wanted(domain, skeleton, only):
        return None
    labels = entry.get("labels")
    try:
        return retarget(
            motion, skeleton, joint_map, fps=fps, height=height, id=str(entry["id"]),
            texts=list(entry.get("texts") or []), labels=labels if isinstance(labels, dict) else {}, category=domain,
            source=str(path),
        )  # fmt: skip
    except UsageError as e:
        raise SkippedClip(f"unmappable rig: {e}") from None


@DATA_SOURCES.register("bvh-dir")
def bvh_dir_source(
    input: str | None,
    skeleton: Skeleton,
    fps: float,
    joint_map: str | None = None,
    height: float | None = None,
    domain: str | list | None = None,
) -> list[LazyItem | Exception]:
    """Motion files of a folder (BVH, ASF/AMC, DeepMimic), retargeted onto ``skeleton`` at ``fps``."""
    if not input or not Path(input).is_dir():
        raise UsageError(f"the bvh-dir source needs --input FOLDER with motion files, got {input!r}")
    folder = Path(input)
    if joint_map is not None:  # fail early on a bad map, not once per clip
        from omg.retarget import get_joint_map

        jmap = get_joint_map(joint_map)
        if jmap.target != skeleton.name:
            raise UsageError(f"joint map {jmap.name!r} maps onto {jmap.target!r}, "
                             f"but the build targets {skeleton.name!r}")
    manifest = folder / "manifest.json"
    if manifest.exists() or manifest.is_symlink():
        data = read_file(manifest, "", MANIFEST_MAX_BYTES)  # a FIFO or a huge file: one line
        try:
            entries = json.loads(data)["clips"]
        except (ValueError, KeyError, TypeError) as e:
            raise UsageError(f"{manifest}: not a clip manifest ({{\"clips\": [...]}}): {e}") from None
        bad = [i for i, e in enumerate(entries) if not isinstance(e, dict) or "id" not in e or "path" not in e]
        if bad:
            raise UsageError(f"{manifest}: clips {bad[:5]} lack an 'id' or a 'path'")
    else:
        entries = _scan(folder)
    return _items(entries, folder, skeleton, fps, joint_map, height, domain)


def _load(entry: dict, folder: Path, skeleton: Skeleton, fps: float, joint_map, height,
          only) -> Clip | Exception | None:
    try:
        return _import(entry, folder, skeleton, fps, joint_map, height, only)
    except SkippedClip as e:
        return e


def _items(entries, folder, skeleton, fps, joint_map, height, only) -> list[LazyItem | Exception]:
    """One item per entry, read when the build gets to it (in a worker process with --workers)."""
    seen: set[str] = set()
    items: list[LazyItem | Exception] = []
    for entry in entries:
        if isinstance(entry, Exception):
            items.append(entry)
            continue
        clip_id = str(entry["id"])
        if clip_id in seen:
            items.append(SkippedClip(f"duplicate clip id: {folder / entry['path']}: id {clip_id!r} is already taken"))
            continue
        seen.add(clip_id)
        items.append(LazyItem(_load, (entry, folder, skeleton, fps, joint_map, height, only)))
    return items
