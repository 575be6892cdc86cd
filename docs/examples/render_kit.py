"""Render a kit's assembly (`links export ... --format 3d`) to a PNG, as the building guide's
picture was made: `python docs/examples/render_kit.py KIT_FOLDER OUT.png`.

Reads the folder's `assembly.glb` (metres, y up, as glTF is) with trimesh and draws every part
at its starting pose with matplotlib, links coloured by layer.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as pyplot
import numpy as np
import trimesh
from mpl_toolkits.mplot3d.art3d import Poly3DCollection


def render(folder: Path, out: Path) -> None:
    """Draw the assembly of the kit in `folder` into the PNG `out`."""
    bom = json.loads((folder / "bom.json").read_text())
    layer_of = {
        f"link-{a}-{b}": link["layer"] for link in bom["links"] for a, b in [link["joints"]]
    }
    colours = pyplot.get_cmap("viridis")(np.linspace(0.1, 0.9, max(bom["layers"], 1)))
    scene = trimesh.load(folder / "assembly.glb")
    figure = pyplot.figure(figsize=(8, 6), dpi=120)
    axes = figure.add_subplot(projection="3d")
    corners = []
    for mesh in scene.dump():
        name, node = mesh.metadata.get("name", ""), mesh.metadata.get("node", "")
        # glTF's y is up: the kit's (x, y, z) in mm is (x, -z, y) of the file, times 1000.
        points = mesh.vertices[:, [0, 2, 1]] * np.array([1e3, -1e3, 1e3])
        corners.append(points)
        if name.startswith("link"):
            colour = colours[layer_of[node]]
        elif name.startswith("pin"):
            colour = (0.35, 0.35, 0.38, 1.0)
        else:
            colour = (0.85, 0.55, 0.25, 1.0)
        axes.add_collection3d(
            Poly3DCollection(points[mesh.faces], facecolor=colour, edgecolor="none", alpha=0.95)
        )
    every = np.concatenate(corners)
    low, high = every.min(axis=0), every.max(axis=0)
    for set_limits, (start, end) in zip(
        (axes.set_xlim, axes.set_ylim, axes.set_zlim), zip(low, high, strict=True), strict=True
    ):
        set_limits(start, end)
    # True proportions across the plane; the stack's height drawn three times over, to be seen.
    axes.set_box_aspect(tuple((high - low) * np.array([1.0, 1.0, 3.0])))
    axes.view_init(elev=30, azim=-65)
    axes.set_zticks([0.0, round(float(high[2]), 1)])
    axes.set_xlabel("x (mm)")
    axes.set_ylabel("y (mm)")
    axes.set_zlabel("z (mm)")
    axes.set_title(f"{len(bom['links'])} links on {bom['layers']} layers", fontsize=10)
    figure.tight_layout()
    figure.savefig(out)


if __name__ == "__main__":
    render(Path(sys.argv[1]), Path(sys.argv[2]))
