"""``omg bench following``: the prompt-following check on real clips, which bounds its own error."""

from __future__ import annotations

from pathlib import Path

from omg.errors import UsageError
from omg.tools.args import PositiveFiniteFloat


def bench_following(input: Path, prompts: Path | None = None, label: str = "content",
                    fps: PositiveFiniteFloat = 20.0, mirror: bool = False) -> list[dict]:
    """The prompt-following check (``omg.metrics.following``) on real clips: every clip of a folder
    (the bvh-dir source: motion files with a manifest.json of labels) whose ``label`` has targets
    under the prompt file's ``labels:`` is read onto SMPL-22 and scored. Real clips of a class
    should pass their own targets: the fraction that does bounds the check's own error. Prints
    one Markdown row per label value and the overall fraction.

    Args:
        input: a folder of motion files with a manifest.json (e.g. ../shared/data/bandai1)
        prompts: the prompt file whose ``labels:`` give the targets (default: the built-in set)
        label: the clip label that names the action (a Bandai-Namco take's ``content``)
        fps: the rate the clips are resampled to
        mirror: score each clip's mirror image against its mirrored label ("walk-left" -> "walk-right")

    Returns:
        One row per label value: label, passed, clips, failed (the ids of the clips that fail).
    """
    import torch

    from omg.data.sources.bvh_dir import bvh_dir_source
    from omg.metrics.following import Joints, label_targets, passes
    from omg.skeleton import SMPL22
    from omg.text.sides import mirror_caption

    table, at = label_targets(prompts), Joints()
    rows: dict[str, dict] = {}
    for item in bvh_dir_source(str(input), SMPL22, fps):
        clip = item() if callable(item) else item
        if clip is None or isinstance(clip, Exception):
            continue
        value = str(clip.labels.get(label))
        joints = torch.from_numpy(clip.positions)
        if mirror:
            value, joints = mirror_caption(value), SMPL22.mirror(joints)
        if value not in table:
            continue
        ok = all(passes(joints, target, fps, at) for target in table[value])
        row = rows.setdefault(value, {"label": value, "passed": 0, "clips": 0, "failed": []})
        row["passed"], row["clips"] = row["passed"] + ok, row["clips"] + 1
        if not ok:
            row["failed"].append(clip.id)
    if not rows:
        raise UsageError(f"--input {input}: no clip has a {label!r} label with targets in the prompt file "
                         f"(labels: {', '.join(table)})")
    print(f"| {label} | targets | real clips passing |\n|---|---|---:|")
    for value, row in sorted(rows.items()):
        targets = "; ".join(", ".join(f"{k}: {v}" for k, v in t.items()) for t in table[value])
        print(f"| {value} | {targets} | {row['passed']}/{row['clips']} |")
    passed, clips = sum(r["passed"] for r in rows.values()), sum(r["clips"] for r in rows.values())
    print(f"| all | | {passed}/{clips} ({passed / clips:.2f}) |")
    return list(rows.values())
