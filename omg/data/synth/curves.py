"""Scalar easing curves over time, the building blocks every channel is keyed with.

All of them are vectorised: ``time`` may be a scalar or an array of seconds, and the result has its shape.
"""

from __future__ import annotations

import numpy as np


def smoothstep(x):
    """Smoothstep on [0, 1], clamped outside: 0 before, 1 after, zero slope at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def window(time, start, end, ramp):
    """1 on [start, end] with smooth ramps of ``ramp`` seconds outside it (0 beyond the ramps)."""
    return smoothstep((time - start + ramp) / ramp) * smoothstep((end - time + ramp) / ramp)


def bump(time, center, half_width):
    """Raised cosine, 1 at ``center`` and exactly 0 beyond ``half_width``: one short gesture."""
    x = np.clip((time - center) / half_width, -1.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def lower_envelope(values: np.ndarray, radius: int) -> np.ndarray:
    """A smooth curve that never exceeds ``values`` (N,): a min-filter of ``radius`` frames, then a
    Hann window of the same radius. The min-filter first makes the smoothing unable to lift the
    curve above any sample, so a root height bounded by leg reach stays bounded."""
    padded = np.pad(values, radius, mode="edge")
    eroded = np.lib.stride_tricks.sliding_window_view(padded, 2 * radius + 1).min(-1)
    kernel = np.hanning(2 * radius + 3)[1:-1]
    return np.convolve(np.pad(eroded, radius, mode="edge"), kernel / kernel.sum(), mode="valid")
