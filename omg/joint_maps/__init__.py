"""Built-in joint maps, one YAML file each (``<name>.yaml``, format in ``omg.retarget``).

Importing this package registers every file here in ``omg.registry.JOINT_MAPS`` under its
stem; a plugin adds its own with ``JOINT_MAPS.register("my_rig", path_or_joint_map)``.
"""

from __future__ import annotations

from pathlib import Path

from omg.registry import JOINT_MAPS

for _path in sorted(Path(__file__).parent.glob("*.yaml")):
    JOINT_MAPS.register(_path.stem, _path)
