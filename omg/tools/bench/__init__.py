"""``omg bench``: speed and memory measurements whose figures go into docs/results/.

Every benchmark makes its own inputs (no dataset download) and prints one Markdown table row
per measurement, with the command that reproduces it. One module per subcommand (``data``,
``train``, ``sample``, ``quality``, ``following``, ``sides``, ``rig``, ``character``, ``timeline``,
``control``, ``gpu``; ``plan`` is ``omg.tools.plan``); ``measure`` holds what they share (a worker
process run with its memory sampled); the device's peaks are in ``omg.tools.devices``. ``python -m
omg.tools.bench`` is the data benchmark's worker: one loader measured in its own process
(``data.loader_worker``).
"""

from __future__ import annotations

from omg.tools.args import run_subcommands
from omg.tools.bench.character import bench_character
from omg.tools.bench.control import bench_control
from omg.tools.bench.data import bench_data
from omg.tools.bench.following import bench_following
from omg.tools.bench.gpu import bench_gpu
from omg.tools.bench.quality import bench_quality
from omg.tools.bench.rig import RIG_CLIPS, bench_rig, rig_round_trips
from omg.tools.bench.sample import bench_sample
from omg.tools.bench.sides import bench_sides
from omg.tools.bench.timeline import bench_timeline
from omg.tools.bench.train import bench_train
from omg.tools.plan import bench_plan

__all__ = ["BENCHMARKS", "RIG_CLIPS", "bench_character", "bench_control", "bench_data", "bench_following",
           "bench_gpu", "bench_plan", "bench_quality", "bench_rig", "bench_sample", "bench_sides", "bench_timeline",
           "bench_train", "main", "rig_round_trips"]

BENCHMARKS = {"data": (bench_data, {}), "train": (bench_train, {}), "sample": (bench_sample, {}),
              "quality": (bench_quality, {}), "following": (bench_following, {}), "sides": (bench_sides, {}),
              "plan": (bench_plan, {}), "gpu": (bench_gpu, {}), "rig": (bench_rig, {}),
              "character": (bench_character, {}), "timeline": (bench_timeline, {}), "control": (bench_control, {})}


def main(argv: list[str]) -> None:
    run_subcommands("omg bench", "Speed and memory measurements (one Markdown table row per measurement).",
                    BENCHMARKS, argv)
