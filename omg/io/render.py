"""Stick-figure previews of motions as animated GIFs (matplotlib Agg + Pillow).

Y is up in omg and Z up in matplotlib's 3D axes, so a joint (x, y, z) is drawn at
(x, z, y), with the x axis reversed to undo the mirroring of that swap. Each panel watches
a travelling motion from the side of its path and one that stays in place from its front
left (a motion faces +Z in its rest pose).
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.animation import PillowWriter
from matplotlib.figure import Figure

from omg.files import atomic_path
from omg.skeleton import Skeleton, get_skeleton

PANEL_INCHES = (3.0, 3.3)  # width, height of one motion's panel
GRID_STEP = 0.5  # metres between floor grid lines
TOP = 0.84  # of the figure's height: the axes below, the caption above
CAPTION_WIDTH, CAPTION_LINES = 36, 3  # characters per line, lines kept
COLORS = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


def _caption(text: str) -> str:
    return "\n".join(textwrap.wrap(text, CAPTION_WIDTH, max_lines=CAPTION_LINES, placeholder=" …"))


def _segments(skeleton: Skeleton) -> list[tuple[int, ...]]:
    """Polylines to draw: the skeleton's chains, else one line per bone."""
    return list(skeleton.chains) or [(p, j) for j, p in enumerate(skeleton.parents) if p >= 0]


def _floor(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(T, J, 3) -> floor corners low (x, z), high (x, z) around the whole motion, and its height."""
    height = max(float(motion[..., 1].max()), 0.0) + 0.1
    xz = motion[..., [0, 2]].reshape(-1, 2)
    centre, half = 0.5 * (xz.min(0) + xz.max(0)), 0.5 * (xz.max(0) - xz.min(0))
    half = np.maximum(half + 0.1, 0.35 * height)  # room around a motion that stays in place
    return centre - half, centre + half, height


def _floor_grid(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(N, 3) plot points of a grid at height 0 with GRID_STEP spacing, NaN rows splitting the lines."""
    xs, zs = (np.arange(np.ceil(lo / GRID_STEP), np.floor(hi / GRID_STEP) + 1) * GRID_STEP for lo, hi in zip(low, high))
    segments = [((x, low[1]), (x, high[1])) for x in xs] + [((low[0], z), (high[0], z)) for z in zs]
    return np.concatenate([[(*a, 0.0), (*b, 0.0), (np.nan,) * 3] for a, b in segments])


def render_gif(
    path: str | Path,
    motions: Sequence[np.ndarray],  # each (T, J, 3) metres, Y up
    skeleton: Skeleton | str,
    fps: float,
    titles: Sequence[str] | None = None,
    max_frames: int = 60,
    dpi: int = 60,
) -> Path:
    """Write the motions side by side as one GIF, atomically; returns ``path``.

    Frames are subsampled to at most ``max_frames`` (GIF time stays real time); a shorter
    motion holds its last pose. Each panel keeps fixed limits, a floor grid at y = 0 and
    the root's trajectory drawn on the floor.
    """
    skel = get_skeleton(skeleton)
    motions = [np.asarray(m, dtype=np.float32) for m in motions]
    if not motions or any(m.ndim != 3 or m.shape[1:] != (skel.num_joints, 3) or not len(m) for m in motions):
        raise ValueError(f"render_gif: motions must be non-empty (T, {skel.num_joints}, 3) arrays, "
                         f"got {[m.shape for m in motions]}")  # fmt: skip
    titles = list(titles) if titles is not None else [""] * len(motions)
    if len(titles) != len(motions):
        raise ValueError(f"render_gif: {len(titles)} titles for {len(motions)} motions")
    length = max(len(m) for m in motions)
    step = math.ceil(length / max_frames)
    frames = range(0, length, step)

    fig = Figure(figsize=(PANEL_INCHES[0] * len(motions), PANEL_INCHES[1]), dpi=dpi)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=TOP, wspace=0)
    segments = _segments(skel)
    panels = []  # per motion: (motion, its lines)
    for i, (motion, title) in enumerate(zip(motions, titles)):
        fig.text((i + 0.5) / len(motions), 0.98, _caption(title), ha="center", va="top", fontsize=8)
        ax = fig.add_subplot(1, len(motions), i + 1, projection="3d")
        ax.set_axis_off()  # our own floor grid instead of the axes' panes: clearer and faster
        low, high, height = _floor(motion)
        ax.set(xlim=(high[0], low[0]), ylim=(low[1], high[1]), zlim=(0, height))
        ax.set_box_aspect((*(high - low), height), zoom=1.1)
        # a travelling motion is watched from the side of its path, one in place from the front
        # left; x is reversed, so azim 90 looks from +Z (the front), 180 from +X (the left)
        width, depth = high - low
        ax.view_init(elev=15, azim=70 + 90 * depth / (width + depth))
        ax.plot(*_floor_grid(low, high).T, color="0.8", lw=0.6)
        ax.plot(motion[:, 0, 0], motion[:, 0, 2], np.zeros(len(motion)), color="0.45", lw=1.0)
        lines = [ax.plot([], [], [], color=COLORS[k % len(COLORS)], lw=2.0, marker="o", ms=2)[0]
                 for k in range(len(segments))]  # fmt: skip
        panels.append((motion, lines))

    path = Path(path)
    writer = PillowWriter(fps=fps / step)
    with atomic_path(path) as tmp, writer.saving(fig, str(tmp), dpi):
        for t in frames:
            for motion, lines in panels:
                pose = motion[min(t, len(motion) - 1)]  # (J, 3)
                for line, chain in zip(lines, segments):
                    xyz = pose[list(chain)]  # (len(chain), 3)
                    line.set_data_3d(xyz[:, 0], xyz[:, 2], xyz[:, 1])
            writer.grab_frame()
    return path
