"""A kit's parts (`engine.fabrication.kit`) as meshes: an STL file a part to print, the whole
assembly as one glTF binary, the bill of materials beside them; written to a folder, or held in
memory (and zipped) for the HTTP API.

The solids are made by manifold3d, whose booleans and extrusions give closed, manifold meshes
(each part watertight by construction), and written by trimesh (binary STL, and glTF 2.0's
binary GLB). Circles are polygons of `CIRCLE_SEGMENTS` sides: a polygon inscribed in a circle
misses (2 pi / n)^2 / 6 of its area, 0.04% at 128, and a hole drawn so is that much smaller.

A link's part lies along +x from its lower joint, at the origin, z from 0 up; a pin's and a
spacer's stand on the origin; the base plate is made where it goes. The assembly places each
as `Kit.placements` says, in a node named after it (`link-I-J`, `pin-J`,
`spacer-J-A-B`, `base`) under one root node, `assembly`, that turns the assembly's z up into
glTF's y up and its millimetres into glTF's metres: a viewer shows it upright at its size.

manifold3d and trimesh are the `build` extra's (`pip install 'links-ray[build]'`), imported
here only when a part is made.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.fabrication.kit import (
    ASSEMBLY_FILE,
    BOM_FILE,
    PARTS_FOLDER,
    Kit,
    KitOptions,
    link_name,
    part_file,
    plan_kit,
)

if TYPE_CHECKING:  # only types here: the libraries are imported when a part is made
    import manifold3d
    import trimesh

__all__ = [
    "CIRCLE_SEGMENTS",
    "assembly_glb",
    "export_kit",
    "kit_files",
    "kit_zip",
    "part_meshes",
]

#: Sides of every circle's polygon: bar ends, holes, pins, spacers.
CIRCLE_SEGMENTS = 128
#: The root node's matrix: z up to glTF's y up ((x, y, z) -> (x, z, -y)), millimetres to metres.
GLTF_ROOT = np.array(
    [[1e-3, 0, 0, 0], [0, 0, 1e-3, 0], [0, -1e-3, 0, 0], [0, 0, 0, 1.0]], dtype=np.float64
)


def _libraries() -> tuple[Any, Any]:
    """(manifold3d, trimesh), or ImportError saying how to install them."""
    try:
        import manifold3d
        import trimesh
    except ImportError as exc:
        raise ImportError(
            f"3D parts need manifold3d and trimesh ({exc.name} is missing): "
            "pip install 'links-ray[build]'"
        ) from None
    return manifold3d, trimesh


def _disc(radius: float, x: float = 0.0, y: float = 0.0) -> manifold3d.CrossSection:
    manifold3d, _ = _libraries()
    return manifold3d.CrossSection.circle(radius, CIRCLE_SEGMENTS).translate((x, y))


def link_solid(length: float, options: KitOptions) -> manifold3d.Manifold:
    """A link's bar: the stadium `bar_width_mm` wide around (0, 0)-(length, 0), less a hole
    at each end, `layer_thickness_mm` thick."""
    manifold3d, _ = _libraries()
    radius, hole = options.bar_width_mm / 2, options.hole_diameter_mm / 2
    bar = manifold3d.CrossSection.batch_hull([_disc(radius), _disc(radius, length)])
    return (bar - _disc(hole) - _disc(hole, length)).extrude(options.layer_thickness_mm)


def tube_solid(outer: float, inner: float | None, height: float) -> manifold3d.Manifold:
    """A cylinder `outer` across (a tube with a bore `inner` across), `height` tall, on the
    origin."""
    section = _disc(outer / 2)
    if inner is not None:
        section = section - _disc(inner / 2)
    return section.extrude(height)


def base_solid(kit: Kit) -> manifold3d.Manifold:
    """The base plate over its extent, a hole the pins' diameter at each post, a layer thick,
    its bottom at z = 0."""
    manifold3d, _ = _libraries()
    if kit.base is None:
        raise ValueError("the kit has no base plate: it was planned without ground_on_base")
    low_x, low_y, high_x, high_y = kit.base.extent_mm
    plate = manifold3d.CrossSection.square((high_x - low_x, high_y - low_y)).translate(
        (low_x, low_y)
    )
    radius = kit.options.pin_diameter_mm / 2
    for joint in kit.base.posts:
        x, y = kit.drawing.joints_mm[joint]
        plate = plate - _disc(radius, float(x), float(y))
    return plate.extrude(kit.options.layer_thickness_mm)


def part_solids(kit: Kit) -> dict[str, manifold3d.Manifold]:
    """Every part's solid in its own frame, by part name (`Placement.part`)."""
    options = kit.options
    lengths = {link.joints: link.length_mm for link in kit.drawing.links}
    solids = {}
    for i, j in kit.plan.links.tolist():
        solids[link_name(i, j)] = link_solid(lengths[(i, j)], options)
    for pin in kit.pins:
        solids[pin.node] = tube_solid(options.pin_diameter_mm, None, pin.length_mm)
    for spacer in kit.spacers:
        if spacer.part not in solids:
            solids[spacer.part] = tube_solid(
                options.spacer_diameter_mm, options.hole_diameter_mm, spacer.length_mm
            )
    if kit.base is not None:
        solids["base"] = base_solid(kit)
    return solids


def part_meshes(kit: Kit) -> dict[str, trimesh.Trimesh]:
    """Every part's mesh in its own frame, in millimetres, by part name; ValueError if one
    cannot be made closed."""
    _, trimesh = _libraries()
    meshes = {}
    for name, solid in part_solids(kit).items():
        mesh = solid.to_mesh64()
        made = trimesh.Trimesh(
            vertices=np.asarray(mesh.vert_properties)[:, :3],
            faces=np.asarray(mesh.tri_verts),
            process=False,  # manifold3d's mesh is closed and shares its vertices already
        )
        # Sizes far apart (a bar a billionth of its length wide) leave float64 no room.
        if solid.is_empty() or not made.is_watertight:
            raise ValueError(
                f"part {name} cannot be made as a closed solid at these sizes: they differ "
                "too much from each other or from the links' lengths"
            )
        meshes[name] = made
    return meshes


def assembly_glb(kit: Kit, meshes: dict[str, trimesh.Trimesh]) -> bytes:
    """The assembly at its starting pose as a glTF binary: each part's mesh placed in its
    node (the module's docstring), under the root node `assembly`."""
    _, trimesh = _libraries()
    scene = trimesh.Scene()
    scene.graph.update(frame_from=scene.graph.base_frame, frame_to="assembly", matrix=GLTF_ROOT)
    for placement in kit.placements():
        scene.add_geometry(
            meshes[placement.part],
            node_name=placement.node,
            geom_name=placement.part,
            parent_node_name="assembly",
            transform=placement.matrix,
        )
    return scene.export(file_type="glb")


def kit_files(kit: Kit) -> dict[str, bytes]:
    """The kit's files by path in its folder: `bom.json`, `assembly.glb` and
    `parts/<part>.stl`, each part once."""
    meshes = part_meshes(kit)
    files = {BOM_FILE: (json.dumps(kit.bom(), indent=1) + "\n").encode()}
    files[ASSEMBLY_FILE] = assembly_glb(kit, meshes)
    for name, mesh in sorted(meshes.items()):
        files[part_file(name)] = mesh.export(file_type="stl")
    return files


def kit_zip(files: dict[str, bytes], folder: str = "kit") -> bytes:
    """`files` (`kit_files`) as a zip archive, in `folder`."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, data in files.items():
            archive.writestr(f"{folder}/{name}", data)
    return buffer.getvalue()


def export_kit(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    out_dir: str | Path,
    options: KitOptions | None = None,
) -> dict[str, Any]:
    """Plan the mechanism as printed parts (`engine.fabrication.kit.plan_kit`) and write
    `bom.json`, `assembly.glb` and `parts/*.stl` into the folder `out_dir`; the bill of
    materials, as written.

    `out_dir` is made if missing; one that holds files must hold an earlier kit (a
    `bom.json`), whose parts are replaced. Raises, before any file is written, `ValueError`
    naming the problem (what `plan_kit` refuses, `LayeringError` among it, a part that cannot
    be made closed, a folder it may not write into) and `ImportError` without the `build`
    extra; `OSError` if a file cannot be written.
    """
    _libraries()  # before the plan, which may take seconds, as the folder's check
    out = Path(out_dir)
    stale = earlier_parts(out)
    kit = plan_kit(adjacency, node_types, positions, options)
    files = kit_files(kit)
    (out / PARTS_FOLDER).mkdir(parents=True, exist_ok=True)
    # Only the parts an earlier kit's bill named: no other file is ever removed.
    for name in stale - set(files):
        (out / name).unlink(missing_ok=True)
    for name, data in files.items():
        (out / name).write_bytes(data)
    return kit.bom()


def earlier_parts(out: Path) -> set[str]:
    """The part files the bill of an earlier kit in the folder `out` names (none for a
    folder that is missing or empty), or ValueError if `out` is no folder, or holds files but
    no earlier kit."""
    if not out.exists():
        return set()
    if not out.is_dir():
        raise ValueError(f"{out} is not a folder")
    if not any(out.iterdir()):
        return set()
    bill = out / BOM_FILE
    refusal = f"{out} holds files but no earlier kit ({BOM_FILE}): give a new or empty folder"
    try:
        parts = json.loads(bill.read_text())["parts"]
    except (OSError, ValueError, KeyError, TypeError):
        raise ValueError(refusal) from None
    if not isinstance(parts, list):
        raise ValueError(refusal)
    # Only names this module writes: a bill edited by hand cannot point outside `parts/`.
    return {
        name
        for name in parts
        if isinstance(name, str)
        and PurePosixPath(name).parent == PurePosixPath(PARTS_FOLDER)
        and name.endswith(".stl")
        and ".." not in name
    }
