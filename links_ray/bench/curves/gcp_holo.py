"""GCP-HOLO's published path-synthesis curves, the field's benchmark for `links bench
synthesize --set`: its eight test curves and its four walking-mechanism foot paths.

The points are stored in `gcp_holo_curves.json` beside this module, with their source: the
GCP-HOLO repository of Fogelson, Tucker and Cagan, at a named commit, under that project's
noncommercial research license. They are used only as targets to measure synthesis against.

Pure json and numpy.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: The stored curves and their source.
CURVES_FILE = Path(__file__).with_name("gcp_holo_curves.json")
#: What every GCP-HOLO curve's name starts with.
FIELD_PREFIX = "holo_"


def gcp_holo_source() -> dict[str, str]:
    """Where the curves come from: repository, commit, files, authors, license, how read."""
    return json.loads(CURVES_FILE.read_text())["source"]


def gcp_holo_curves() -> dict[str, dict[str, np.ndarray]]:
    """The curves by family (`test`, `gait`), each named `holo_<name>` (`holo_eight`,
    `holo_gait_jansen`): (N, 2) closed polylines, not repeating their first point, in
    GCP-HOLO's own order and units."""
    stored = json.loads(CURVES_FILE.read_text())
    return {
        "test": {
            f"{FIELD_PREFIX}{name}": np.array(points) for name, points in stored["test"].items()
        },
        "gait": {
            f"{FIELD_PREFIX}gait_{name}": np.array(points)
            for name, points in stored["gait"].items()
        },
    }
