"""The order the suite hands its tests to the xdist workers (``conftest.pytest_collection_modifyitems``).

`--dist loadgroup` sends work in collection order, one unit at a time: a test, or a whole ``xdist_group``
(its tests run on one worker, which builds their shared fixtures once). A long unit that starts last ends
the run late by its whole length, so the units are sorted longest first: the long ones start at once, on
separate workers, and the short tests fill the time around them."""

from __future__ import annotations

import pytest

# Seconds a test or a whole xdist group takes on the CI machine (2 cores, the other workers busy beside
# it), its fixtures included: from the durations of `.ci/run`'s pytest. Only the order comes from these,
# so a rough figure does; a test marked `slow` that is not here counts SLOW_SECONDS. A key is an xdist
# group's name, "file::test" (each of its parameter cases) or "file::test[case]".
LONGEST: dict[str, float] = {
    "test_multinode.py::test_torchrun_node_lost_mid_run_ends_the_other_in_one_line_and_resumes": 150,
    "test_real_learning.py::test_held_out_prompts_give_walking_backward_and_bowing": 150,
    "serve": 140,
    "habit": 130,
    "omgpt": 90,
    "evaluator": 60,
    "ddp_resume": 45,
    "test_callbacks.py::test_controlnet_samples_follow_lengths_and_guidance": 45,
    "test_launch.py::test_devices_2_on_one_machine_starts_both_ranks_from_any_folder": 45,
    "outside": 45,
    "controlnet_module": 40,
    "public_api": 40,
    "pretrain_whole_run": 35,
    "build_scale": 30,
    "test_datamodule.py::test_two_ranks_read_disjoint_shards_and_equal_batch_counts": 28,
    "fbx": 25,
    "docs": 20,
    "retarget": 20,
    "test_plan.py::test_controlnet_activation_estimate_matches_the_measured_peak": 16,
    "test_plan.py::test_activation_estimate_matches_the_measured_peak[8-256-True]": 15,
    "test_bench.py::test_the_data_benchmark_runs_its_workers_by_module_path": 15,
    "test_bvh_dir.py::test_real_manifest_builds": 13,
    "test_gpu_check.py::test_dry_run_resolves_every_command_and_trains_nothing": 12,
    "test_mini_data.py::test_committed_mini_data_matches_the_generator": 12,
    "checkpoint_safety": 12,
    "gltf_character": 10,
    "test_run_faults.py::test_ctrl_c_saves_a_checkpoint_exits_130_and_resumes": 10,
}
SLOW_SECONDS = 30.0  # the `slow` marker's "half a minute or more"


def unit_of(item: pytest.Item) -> str:
    """What xdist sends a worker at once (``--dist loadgroup``): the item's xdist group, or the item alone."""
    mark = item.get_closest_marker("xdist_group")
    if mark is None:
        return item.nodeid
    return "group " + (mark.args[0] if mark.args else mark.kwargs.get("name", "default"))


def own_seconds(item: pytest.Item) -> float:
    """What LONGEST says of this test alone (0 for a short one)."""
    for key in (f"{item.path.name}::{item.name}", f"{item.path.name}::{getattr(item, 'originalname', item.name)}"):
        if key in LONGEST:
            return LONGEST[key]
    return SLOW_SECONDS if item.get_closest_marker("slow") else 0.0


def unit_seconds(items: list[pytest.Item]) -> dict[str, float]:
    """Each unit's seconds: a test's own, a group's from LONGEST or else the sum of its tests'."""
    seconds: dict[str, float] = {}
    for item in items:
        unit = unit_of(item)
        seconds[unit] = seconds.get(unit, 0.0) + own_seconds(item)
    return {unit: LONGEST.get(unit.removeprefix("group "), s) if unit.startswith("group ") else s
            for unit, s in seconds.items()}


def longest_first(items: list[pytest.Item]) -> None:
    """Sort ``items`` in place by their unit's seconds, longest first. Units of equal seconds keep their
    collection order; a group's tests sort together (xdist places a group where its first test is)."""
    seconds = unit_seconds(items)
    first: dict[str, int] = {}
    for index, item in enumerate(items):
        first.setdefault(unit_of(item), index)
    items.sort(key=lambda item: (-seconds[unit_of(item)], first[unit_of(item)]))
