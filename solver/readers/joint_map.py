"""Reader for a joint map (``posecast eval --map FILE``): file joint name -> canonical role.

For a rig whose names no table of ``solver/naming.py`` knows and whose shape misleads. A
flat table, JSON or TOML by the file's suffix::

    {"Bone_017": "forearm_l", "Bone_018": "hand_l"}        # map.json
    "mixamorig1:LeftForeArm" = "forearm_l"                    # map.toml

Roles are those of ``naming.ROLES`` (spine and neck may be given to several joints);
"" says a joint plays no role. Joints the map leaves out are matched by name and shape
as usual; names a file lacks are ignored, so that one map serves several exports of a rig.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

from posecast.solver.naming import ROLES
from posecast.solver.readers.errors import FormatError


def read_joint_map(path: str | Path) -> dict[str, str]:
    src = str(path)
    suffix = Path(path).suffix.lower()
    if suffix not in (".json", ".toml"):
        raise FormatError(src, None, "a joint map is a .json or .toml file")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise FormatError(src, None, "not UTF-8 text") from None
    try:
        data = json.loads(text) if suffix == ".json" else tomllib.loads(text)
    except json.JSONDecodeError as err:
        raise FormatError(src, err.lineno, f"not JSON: {err.msg}") from None
    except tomllib.TOMLDecodeError as err:
        raise FormatError(src, None, f"not TOML: {err}") from None
    if not isinstance(data, dict):
        raise FormatError(src, None, "expected a table of joint name -> role")
    for name, role in data.items():
        if not isinstance(role, str) or (role and role not in ROLES):
            raise FormatError(src, None, f"joint {name!r}: role {role!r} is none of "
                                         f"{', '.join(ROLES)} (or \"\" for no role)")
    return dict(data)
