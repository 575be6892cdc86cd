"""A kit of printable parts and its assembly (engine/fabrication/kit.py, interop/parts.py): every
part a closed solid of the size its outline says, the bill of materials the layer plan, and no two
parts nearer than the clearance at 360 poses of a turn.

The files are read back with trimesh (STL and GLB), and each part's section at mid-height is
rebuilt from its mesh's triangles with shapely; the truth comes from closed forms, from the
raw positions scaled here, and from `plan_layers` called directly. The poses are halfway
between the planner's 360 steps.
"""

from __future__ import annotations

import itertools
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.kit import KitOptions, plan_kit
from links_ray.engine.fabrication.layers import LayeringError, plan_layers
from links_ray.engine.kinematics.topology import random_topology
from links_ray.interop.parts import GLTF_ROOT, export_kit, kit_files, kit_zip
from tests.support.needs import need_module
from tests.support.serving import FOUR_BAR

trimesh = need_module("trimesh", "pip install 'links-ray[build]' (the test extra)")
shapely = need_module("shapely", "pip install shapely (the test extra)")
need_module("manifold3d", "pip install 'links-ray[build]' (the test extra)")


def random_mechanism(seed: int, joints: int) -> dict[str, Any]:
    adjacency, node_types = random_topology(seed, joints)
    positions = links_ray.sample_positions(adjacency, node_types, count=1, seed=seed)[0]
    return {"adjacency": adjacency, "node_types": node_types, "positions": positions}


#: (mechanism, options): a four-bar; 12 joints standing on a base plate; 11 joints, narrower
#: bars, no layer gap; each builds in under a second.
BUILDS = {
    "four-bar": (FOUR_BAR, KitOptions(crank_mm=25)),
    "12 joints on a base": (random_mechanism(4, 12), KitOptions(ground_on_base=True)),
    "11 joints, no gap": (
        random_mechanism(13, 11),
        KitOptions(bar_width_mm=7, spacer_diameter_mm=5.5, layer_gap_mm=0, clearance_mm=0.5),
    ),
}
#: No order of layers keeps every pin clear (with the default sizes, a 20 mm crank).
UNBUILDABLE = random_mechanism(25, 8)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict[str, Any]]]:
    """Each build exported once: its folder and its bill of materials."""
    found = {}
    for name, (mechanism, options) in BUILDS.items():
        folder = tmp_path_factory.mktemp("build")
        found[name] = (folder, export_kit(**mechanism, out_dir=folder, options=options))
    return found


def joints_mm(mechanism: dict[str, Any], crank_mm: float) -> np.ndarray:
    """The joints in mm from the raw positions: joint 0 at the origin, the crank `crank_mm`."""
    pos = np.asarray(mechanism["positions"], dtype=float)
    return (pos - pos[0]) * crank_mm / math.dist(pos[0], pos[1])


def section(mesh: Any) -> Any:
    """The part's solid cut at mid-height, as a shapely polygon (with its holes): of the faces
    the cut's segments bound, the largest (the others are the holes' insides)."""
    low, high = mesh.bounds[:, 2]
    lines = trimesh.intersections.mesh_plane(mesh, [0, 0, 1], [0, 0, (low + high) / 2])
    segments = [tuple(map(tuple, np.round(line[:, :2], 7))) for line in lines]
    faces = list(shapely.ops.polygonize(segments))
    return max(faces, key=lambda face: face.area)


# -- the parts ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", BUILDS)
def test_every_part_is_watertight_and_as_big_as_its_outline(
    built: dict[str, tuple[Path, dict[str, Any]]], name: str
) -> None:
    folder, bom = built[name]
    mechanism, options = BUILDS[name]
    joints = joints_mm(mechanism, options.crank_mm)
    width, hole, pin = options.bar_width_mm, options.hole_diameter_mm, options.pin_diameter_mm
    spacer, thickness = options.spacer_diameter_mm, options.layer_thickness_mm
    files = sorted((folder / "parts").glob("*.stl"))
    assert sorted(f"parts/{file.name}" for file in files) == bom["parts"]
    for file in files:
        mesh = trimesh.load(file)
        assert mesh.is_watertight and mesh.is_volume, file.name
        kind, _, rest = file.stem.partition("-")
        height = float(np.ptp(mesh.bounds[:, 2]))
        if kind == "link":
            i, j = map(int, rest.split("-"))
            length = math.dist(joints[i], joints[j])
            # A stadium: a rectangle and two half discs, less two holes.
            area = width * length + math.pi * width**2 / 4 - 2 * math.pi * hole**2 / 4
            assert height == pytest.approx(thickness, rel=1e-12)
        elif kind == "pin":
            area = math.pi * pin**2 / 4
        elif kind == "spacer":
            area = math.pi * (spacer**2 - hole**2) / 4
            assert height == pytest.approx(float(rest.removesuffix("mm")), rel=1e-5)
        else:
            assert file.stem == "base"
            low_x, low_y, high_x, high_y = bom["base"]["extent_mm"]
            posts = len(bom["base"]["posts"])
            area = (high_x - low_x) * (high_y - low_y) - posts * math.pi * pin**2 / 4
        assert mesh.volume == pytest.approx(area * height, rel=1e-3), file.name


# -- the bill of materials ----------------------------------------------------------------------


@pytest.mark.parametrize("name", BUILDS)
def test_the_bill_is_the_layer_plan(
    built: dict[str, tuple[Path, dict[str, Any]]], name: str
) -> None:
    folder, bom = built[name]
    mechanism, options = BUILDS[name]
    assert json.loads((folder / "bom.json").read_text()) == bom
    joints = joints_mm(mechanism, options.crank_mm)
    plan = plan_layers(
        mechanism["adjacency"],
        mechanism["node_types"],
        joints,
        bar_width=options.bar_width_mm,
        clearance=options.clearance_mm,
        pin_diameter=options.spacer_diameter_mm,
        ground_on_base=options.ground_on_base,
    )
    assert (bom["unit"], bom["frame"], bom["assembly"]) == ("mm", "crank", "assembly.glb")
    assert bom["crank_mm"] == options.crank_mm
    assert np.allclose(bom["origin"], mechanism["positions"][0])
    assert (bom["layers"], bom["lower_bound"], bom["optimal"], bom["status"]) == (
        plan.layers,
        plan.lower_bound,
        plan.optimal,
        plan.status,
    )
    for key in ("bar_width", "clearance", "pin_diameter", "hole_diameter", "layer_gap"):
        assert bom[f"{key}_mm"] == getattr(options, f"{key}_mm")
    assert bom["ground_on_base"] is options.ground_on_base
    assert [link["joints"] for link in bom["links"]] == plan.links.tolist()
    assert [link["layer"] for link in bom["links"]] == plan.link_layer.tolist()
    pitch = options.layer_thickness_mm + options.layer_gap_mm
    for link in bom["links"]:
        # The hole spacing, measured on the part (an STL holds float32): its length less the
        # two half widths.
        mesh = trimesh.load(folder / link["part"])
        spacing = float(np.ptp(mesh.bounds[:, 0])) - options.bar_width_mm
        i, j = link["joints"]
        assert spacing == pytest.approx(math.dist(joints[i], joints[j]), rel=1e-6)
        assert link["length_mm"] == pytest.approx(math.dist(joints[i], joints[j]), rel=1e-12)
        assert link["z_mm"] == pytest.approx([link["layer"] * pitch, link["layer"] * pitch + 3])
    with_links = sorted({joint for link in bom["links"] for joint in link["joints"]})
    assert [pin["joint"] for pin in bom["pins"]] == with_links
    for pin in bom["pins"]:
        joint = pin["joint"]
        assert pin["layers"] == plan.pin_span[joint].tolist()
        lo, hi = pin["layers"]
        if pin["post"]:  # from the base plate's bottom to half a gap over its top link
            expected = hi * pitch + options.layer_thickness_mm * 2 + options.layer_gap_mm * 1.5
        else:  # its span and half a gap at each end
            expected = (hi - lo) * pitch + options.layer_thickness_mm + options.layer_gap_mm
        assert pin["length_mm"] == pytest.approx(expected)
        mesh = trimesh.load(folder / pin["part"])
        assert float(np.ptp(mesh.bounds[:, 2])) == pytest.approx(expected)
        # Its links and spacers (and the plate, under a post) stack without a gap or an overlap.
        stack = [link["z_mm"] for link in bom["links"] if joint in link["joints"]]
        stack += [spacer["z_mm"] for spacer in bom["spacers"] if spacer["joint"] == joint]
        if pin["post"]:
            stack.append(bom["base"]["z_mm"])
        stack.sort()
        for (_, top), (bottom, _) in itertools.pairwise(stack):
            assert bottom == pytest.approx(top, abs=1e-9)


# -- the assembly -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", BUILDS)
def test_the_glb_places_every_part_at_its_joints(
    built: dict[str, tuple[Path, dict[str, Any]]], name: str
) -> None:
    """Each node of the GLB holds its part where the bill says, under a root turned z up to y
    up and millimetres to metres: a link's holes on its joints, a pin on its joint."""
    folder, bom = built[name]
    scene = trimesh.load(folder / "assembly.glb")
    nodes = {item["node"]: item for group in ("links", "pins", "spacers") for item in bom[group]}
    if bom["base"] is not None:
        nodes["base"] = bom["base"]
    assert set(scene.graph.nodes_geometry) == set(nodes)
    joints = {joint["joint"]: (joint["x_mm"], joint["y_mm"]) for joint in bom["joints"]}
    unturned = np.linalg.inv(GLTF_ROOT)
    for node, item in nodes.items():
        matrix, _ = scene.graph[node]
        placed = unturned @ matrix
        if node.startswith("link"):
            ends = placed @ np.array([[0, 0, 0, 1], [item["length_mm"], 0, 0, 1]], dtype=float).T
            i, j = item["joints"]
            assert ends[:2].T == pytest.approx(np.array([joints[i], joints[j]]), abs=1e-9)
            assert ends[2] == pytest.approx([item["z_mm"][0]] * 2, abs=1e-9)
        elif node != "base":
            assert placed[:3, 3] == pytest.approx([*joints[item["joint"]], item["z_mm"][0]])


@pytest.mark.parametrize("name", BUILDS)
def test_no_two_parts_come_within_the_clearance_over_a_turn(
    built: dict[str, tuple[Path, dict[str, Any]]], name: str
) -> None:
    """At 360 poses, halfway between the planner's steps, every two parts whose heights
    overlap are at least the clearance apart in the plane, their sections measured; but a pin
    and its own links and spacers, which only must not meet (it turns in their holes), and a
    post in the base plate (a press fit). Parts whose heights do not overlap cannot meet."""
    folder, bom = built[name]
    mechanism, options = BUILDS[name]
    kit = plan_kit(**mechanism, options=options)
    sections = {}
    for file in (folder / "parts").glob("*.stl"):
        mesh = trimesh.load(file)
        sections[file.stem] = (section(mesh), *mesh.bounds[:, 2])
    joint_of = {item["node"]: item.get("joint") for item in bom["pins"] + bom["spacers"]}
    links_at = {link["node"]: set(link["joints"]) for link in bom["links"]}
    turn = links_ray.simulate(
        mechanism["adjacency"], mechanism["node_types"], kit.drawing.joints_mm, 720
    )
    checked = 0
    for step in range(1, 720, 2):
        placed = kit.placements(turn[:, step])
        outlines, heights = [], []
        for placement in placed:
            outline, low, high = sections[placement.part]
            m = placement.matrix
            outlines.append(
                shapely.affinity.affine_transform(
                    outline, [m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[0, 3], m[1, 3]]
                )
            )
            heights.append((low + m[2, 3], high + m[2, 3]))
        shapes, z = np.array(outlines, dtype=object), np.array(heights)
        first, second = np.triu_indices(len(placed), 1)
        overlap = np.minimum(z[first, 1], z[second, 1]) - np.maximum(z[first, 0], z[second, 0])
        reach = options.clearance_mm * np.array([-1, -1, 1, 1])
        box = shapely.bounds(shapes) + reach  # parts whose boxes this far apart are apart
        near = (
            (box[first, 0] <= box[second, 2])
            & (box[second, 0] <= box[first, 2])
            & (box[first, 1] <= box[second, 3])
            & (box[second, 1] <= box[first, 3])
        )
        measured = (overlap > 1e-9) & near
        for a, b in zip(first[measured], second[measured], strict=True):
            names = {placed[a].node, placed[b].node}
            pins = [n for n in names if n.startswith("pin")]
            own = pins and all(
                joint_of.get(n) == joint_of[pins[0]] or joint_of[pins[0]] in links_at.get(n, ())
                for n in names
            )
            if "base" in names and pins:
                continue  # a post stands in its hole in the plate
            if own:
                assert not shapes[a].intersects(shapes[b]), (step, names)
            else:
                gap = shapes[a].distance(shapes[b])
                assert gap >= options.clearance_mm * (1 - 1e-9), (step, names, gap)
            checked += 1
    assert checked > 360  # the near pairs were measured, not skipped


# -- frames, folders and refusals ---------------------------------------------------------------


def test_without_a_crank_length_the_positions_are_the_millimetres(tmp_path: Path) -> None:
    mechanism = {**FOUR_BAR, "positions": (np.asarray(FOUR_BAR["positions"]) * 600).tolist()}
    bom = export_kit(**mechanism, out_dir=tmp_path, options=KitOptions(crank_mm=None))
    assert (bom["frame"], bom["mm_per_unit"], bom["origin"]) == ("drawing", 1.0, [0.0, 0.0])
    kept = [[joint["x_mm"], joint["y_mm"]] for joint in bom["joints"]]
    assert kept == mechanism["positions"]
    assert bom["crank_mm"] == pytest.approx(30)


def test_a_folder_with_other_files_is_refused_and_an_earlier_build_replaced(
    tmp_path: Path,
) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="holds files but no earlier kit"):
        export_kit(**FOUR_BAR, out_dir=tmp_path)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["notes.txt"]
    folder = tmp_path / "build"
    big = export_kit(**random_mechanism(4, 12), out_dir=folder)
    (folder / "parts" / "mine.stl").write_text("not a part of a build")
    small = export_kit(**FOUR_BAR, out_dir=folder)
    left = sorted(f"parts/{path.name}" for path in (folder / "parts").iterdir())
    assert left == sorted([*small["parts"], "parts/mine.stl"])  # the earlier parts are gone
    assert len(big["parts"]) > len(small["parts"])
    (folder / "bom.json").write_text(json.dumps({"parts": ["../notes.txt", "parts/../x.stl"]}))
    export_kit(**FOUR_BAR, out_dir=folder)
    assert (tmp_path / "notes.txt").read_text() == "mine"  # a bill cannot name files outside


def test_an_unbuildable_mechanism_and_bad_options_are_refused(tmp_path: Path) -> None:
    with pytest.raises(LayeringError, match="no layer plan keeps every pin clear"):
        export_kit(**UNBUILDABLE, out_dir=tmp_path / "none")
    assert not (tmp_path / "none").exists()  # nothing is written
    refused = [
        ({"bar_width_mm": 0}, "bar_width_mm must be more than 0"),
        ({"layer_gap_mm": -1}, "layer_gap_mm must be from 0 to 1e+06 mm, got -1"),
        ({"clearance_mm": math.nan}, "clearance_mm must be from 0"),
        ({"hole_diameter_mm": "3"}, "hole_diameter_mm must be a number of millimetres"),
        ({"pin_diameter_mm": 3.5}, "pin_diameter_mm must be less than hole_diameter_mm"),
        ({"spacer_diameter_mm": 9}, "spacer_diameter_mm must be less than bar_width_mm"),
        ({"crank_mm": 0}, "crank_mm must be more than 0"),
        ({"ground_on_base": 1}, "ground_on_base must be true or false"),
    ]
    for change, words in refused:
        with pytest.raises(ValueError, match=re.escape(words)):
            KitOptions(**change)
    with pytest.raises(ValueError, match=re.escape("link [0, 1] is 0.05 mm long: its holes")):
        plan_kit(**FOUR_BAR, options=KitOptions(crank_mm=None))
    tiny = {"bar_width_mm": 1e-10, "spacer_diameter_mm": 9e-11, "hole_diameter_mm": 8e-11}
    tiny_kit = plan_kit(**FOUR_BAR, options=KitOptions(**tiny, pin_diameter_mm=7e-11))
    with pytest.raises(ValueError, match="link-0-1 cannot be made as a closed solid"):
        kit_files(tiny_kit)
    with pytest.raises(ValueError, match="options must be a KitOptions"):
        plan_kit(**FOUR_BAR, options={"bar_width_mm": 8})  # type: ignore[arg-type]


def test_the_zip_holds_the_folder(built: dict[str, tuple[Path, dict[str, Any]]]) -> None:
    import io
    import zipfile

    mechanism, options = BUILDS["four-bar"]
    files = kit_files(plan_kit(**mechanism, options=options))
    folder, bom = built["four-bar"]
    with zipfile.ZipFile(io.BytesIO(kit_zip(files))) as archive:
        names = archive.namelist()
        assert sorted(names) == sorted(
            f"kit/{name}" for name in ["bom.json", "assembly.glb", *bom["parts"]]
        )
        for name in bom["parts"]:
            assert archive.read(f"kit/{name}") == (folder / name).read_bytes()
