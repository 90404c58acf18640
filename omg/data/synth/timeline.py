"""The time grid a clip is keyed on, and the root's path on the floor.

Footprints are placed where the body will be at mid-stance, which can lie before the first or
after the last frame; so every clip is simulated on a padded grid that extends ``PAD_SECONDS``
past both ends, and only the middle ``num_frames`` frames are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omg.data.synth.rig import rotate_by_heading

PAD_SECONDS = 4.0  # simulated before the first and after the last frame
MIN_FRAMES = 8


@dataclass(frozen=True, eq=False)
class Timeline:
    """A clip's frames at ``fps``, inside a padded grid; second 0 is the clip's first frame."""

    fps: float
    duration_s: float  # as planned, before rounding to frames (some ramps are timed from it)
    pad_frames: int  # frames of padding on each side
    num_frames: int  # frames in the clip, T
    padded_seconds: np.ndarray  # (N,) with N = T + 2 * pad_frames

    @classmethod
    def covering(cls, duration_s: float, fps: float) -> Timeline:
        # np.rint rounds half to even, as round() does
        pad_frames, num_frames = int(np.rint(PAD_SECONDS * fps)), max(int(np.rint(duration_s * fps)), MIN_FRAMES)
        padded_seconds = np.arange(-pad_frames, num_frames + pad_frames) / fps
        return cls(fps, duration_s, pad_frames, num_frames, padded_seconds)

    @property
    def frames(self) -> slice:
        """The clip's frames within the padded grid."""
        return slice(self.pad_frames, self.pad_frames + self.num_frames)

    @property
    def seconds(self) -> np.ndarray:
        """(T,) the clip's frame times."""
        return self.padded_seconds[self.frames]

    @property
    def num_padded(self) -> int:
        return len(self.padded_seconds)


@dataclass(frozen=True, eq=False)
class RootPath:
    """The root's floor trajectory on the padded grid."""

    seconds: np.ndarray  # (N,)
    x: np.ndarray  # (N,) metres
    z: np.ndarray  # (N,) metres
    heading: np.ndarray  # (N,) yaw (rad), 0 = facing +Z, positive turns left (towards +X)

    @classmethod
    def integrate(cls, seconds, origin_frame: int, velocity, yaw_rate) -> RootPath:
        """Integrate velocity (N, 2) in the body frame (x left, z forward, m/s) and yaw_rate (N,) (rad/s);
        the path starts at the world origin, facing +Z, at ``seconds[origin_frame]`` (the first clip frame)."""
        step_s = seconds[1] - seconds[0]
        heading = np.cumsum(yaw_rate) * step_s
        heading -= heading[origin_frame]
        velocity_x, velocity_z = rotate_by_heading(heading, velocity[:, 0], velocity[:, 1])
        x, z = np.cumsum(velocity_x) * step_s, np.cumsum(velocity_z) * step_s
        return cls(seconds, x - x[origin_frame], z - z[origin_frame], heading)

    def at(self, query_seconds):
        """(x, z, heading) interpolated at any times, each of the query's shape."""
        return tuple(np.interp(query_seconds, self.seconds, values) for values in (self.x, self.z, self.heading))


@dataclass(frozen=True, eq=False)
class ActionContext:
    """What every action gets: the clip's random generator and frame rate. The draws go through
    these methods, in the order the actions make them: the committed mini shards depend on it."""

    rng: np.random.Generator
    fps: float

    def uniform(self, low: float, high: float) -> float:
        return self.rng.uniform(low, high)

    def pick(self, options):
        return options[self.rng.integers(len(options))]

    def chance(self, probability: float) -> bool:
        return self.rng.random() < probability

    def timeline(self, duration_s: float) -> Timeline:
        return Timeline.covering(duration_s, self.fps)
