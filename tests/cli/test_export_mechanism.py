"""`links export` (cli/export.py): a mechanism from a JSON file, a retrieve or synthesize output,
stdin or a dataset, out as SVG, DXF, a table or a pylinkage script; one-line errors.

Run as the user runs it, `python -m links_ray.cli export ...` in a subprocess. The dataset is
one real committed generation shard (`write_shard`, no Ray).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.data.generation import GenerationPlan, write_shard
from links_ray.data.store import Store
from links_ray.engine.fabrication.drawings import fabrication
from links_ray.interop.drawings import dxf_drawing
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.needs import need_module
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR

SVG = "{http://www.w3.org/2000/svg}"


def links(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "links_ray.cli", "export", *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=300,
    )


def ok(*args: str, stdin: str | None = None) -> str:
    done = links(*args, stdin=stdin)
    assert done.returncode == 0, done.stderr
    return done.stdout


def write_json(path: Path, value: Any) -> str:
    path.write_text(json.dumps(value))
    return str(path)


def svg_links(svg: str) -> dict[tuple[int, int], float]:
    """Each link line's length in mm, measured from its end points."""
    found = {}
    for line in ET.fromstring(svg).iter(f"{SVG}line"):
        i, j = map(int, line.get("data-joints").split())
        x1, y1, x2, y2 = (float(line.get(k)) for k in ("x1", "y1", "x2", "y2"))
        found[i, j] = math.hypot(x2 - x1, y2 - y1)
    return found


def test_table_svg_dxf_and_script_of_a_mechanism_file(tmp_path: Path) -> None:
    source = write_json(tmp_path / "four-bar.json", FOUR_BAR)
    text = ok(source)  # the table by default on stdout
    assert "crank 20 mm" in text and "113.137" in text
    table = json.loads(ok(source, "--json", "--crank-mm", "50"))
    assert [link["length_mm"] for link in table["links"]] == pytest.approx(
        [50, 1000 * math.hypot(0.05, 0.2), 1000 * math.hypot(0.2, 0.2)]
    )
    assert table["path_joint"] is None

    lengths = svg_links(ok(source, "--format", "svg", "--crank-mm", "12.5"))
    assert lengths == pytest.approx(
        {(0, 1): 12.5, (1, 3): 250 * math.hypot(0.05, 0.2), (2, 3): 250 * math.hypot(0.2, 0.2)},
        abs=1e-8,
    )

    # The format from the file's suffix; a path when asked for.
    out = tmp_path / "four-bar.dxf"
    said = ok(source, "--out", str(out), "--path-joint", "3")
    assert said.strip() == f"wrote {out}: dxf, 4 joints, 3 links, crank 20 mm"
    written = read_dxf(out.read_bytes())
    assert written.header["$INSUNITS"] == 4
    # Each file has its own time stamps and GUIDs: the same parts drawn.
    same = read_dxf(dxf_drawing(fabrication(**FOUR_BAR, crank_mm=20, path_joint=3)))
    assert dxf_parts(written) == dxf_parts(same)
    assert [kind for kind, _, _ in dxf_parts(written)].count("LWPOLYLINE") == 1  # the path

    script = tmp_path / "four-bar.py"
    ok(source, "--out", str(script), "--crank-mm", "30")
    pl = need_module("pylinkage", "pip install pylinkage (the test extra)")
    scope: dict[str, Any] = {"__name__": "exported"}
    exec(compile(script.read_text(), str(script), "exec"), scope)
    linkage = scope["linkage"]
    assert isinstance(linkage, pl.Linkage)
    poses = np.array(list(linkage.step()))  # pylinkage yields the pose after each crank step
    truth = (links_ray.simulate(**FOUR_BAR) - [0.5, 0.5]) * 600  # crank 0.05 -> 30 mm
    np.testing.assert_allclose(np.roll(poses, 1, axis=0), truth.transpose(1, 0, 2), atol=1e-6)


def retrieve_output() -> dict[str, Any]:
    """What `links retrieve` prints, its fields as the contract has them, two results."""
    adjacency, node_types = links_ray.random_topology(5)
    positions = links_ray.sample_positions(adjacency, node_types, count=1, seed=5)[0]
    mechanism = {
        "adjacency": adjacency.tolist(),
        "node_types": node_types.tolist(),
        "positions": positions.tolist(),
    }
    last = len(node_types) - 1
    return {
        "results": [
            {"path_id": 7, "mechanism": FOUR_BAR, "mechanism_joint": 3, "chamfer": 0.01},
            {"path_id": 9, "mechanism": mechanism, "mechanism_joint": last, "chamfer": 0.02},
        ],
        "took_ms": 12.0,
    }


def test_a_result_of_retrieve_or_synthesize_with_its_path(tmp_path: Path) -> None:
    output = retrieve_output()
    source = write_json(tmp_path / "results.json", output)
    second = output["results"][1]
    svg = ok(source, "--result", "2", "--format", "svg", "--crank-mm", "15")
    root = ET.fromstring(svg)
    polygon = root.find(f".//{SVG}g[@id='PATH']/{SVG}polygon")
    assert int(polygon.get("data-joint")) == second["mechanism_joint"]  # the result's joint
    points = np.array([p.split(",") for p in polygon.get("points").split()], dtype=float)
    mech = second["mechanism"]
    pos = np.asarray(mech["positions"])
    scale = 15 / math.dist(pos[0], pos[1])
    truth = (links_ray.simulate(**mech)[second["mechanism_joint"]] - pos[0]) * scale
    np.testing.assert_allclose(points, truth, atol=2e-9, rtol=0)
    assert len(svg_links(svg)) == int(np.triu(mech["adjacency"]).sum())
    # The first result by default; --path-joint none leaves the path out; stdin works too.
    assert "<polygon" in ok(source, "--format", "svg")
    assert "<polygon" not in ok(source, "--format", "svg", "--path-joint", "none")
    piped = ok(
        "-", "--format", "svg", "--result", "2", "--crank-mm", "15", stdin=json.dumps(output)
    )
    assert piped == svg
    # A result list alone, and one result alone, are read as well.
    listed = write_json(tmp_path / "list.json", output["results"])
    assert ok(listed, "--result", "2", "--format", "svg", "--crank-mm", "15") == svg
    alone = write_json(tmp_path / "one.json", second)
    assert ok(alone, "--format", "svg", "--crank-mm", "15") == svg


def synthesis_output() -> dict[str, Any]:
    """What `links synthesize --json` prints, one result: a four-bar where a curve was drawn,
    in a drawing's units (its crank 7.5 long, joint 0 at (40, -12))."""
    positions = np.asarray(FOUR_BAR["positions"]) * 150 + [-35, -87]
    mechanism = {**FOUR_BAR, "positions": positions.tolist()}
    result = {"path_id": 7, "mechanism_id": 1, "mechanism": mechanism, "mechanism_joint": 3}
    return {"results": [{**result, "chamfer": 0.01, "retrieved_chamfer": 0.02}], "took_ms": 9.0}


def test_a_result_keeps_the_drawings_frame_unless_given_a_crank(tmp_path: Path) -> None:
    """Without --crank-mm a result's mechanism is drawn where its curve was, the drawing's unit
    a millimetre, in every format; with it, scaled from joint 0 at the origin. A mechanism
    that is not a result still gets a 20 mm crank."""
    output = synthesis_output()
    source = write_json(tmp_path / "found.json", output)
    positions = np.asarray(output["results"][0]["mechanism"]["positions"])
    table = json.loads(ok(source, "--json"))
    assert table["frame"] == "drawing" and table["mm_per_unit"] == 1.0
    assert table["crank_mm"] == pytest.approx(7.5)
    kept = np.array([[joint["x_mm"], joint["y_mm"]] for joint in table["joints"]])
    np.testing.assert_array_equal(kept, positions)
    assert "positions in the drawing's own frame" in ok(source)
    svg = ok(source, "--format", "svg")
    root = ET.fromstring(svg)
    assert "the drawing's own frame" in root.find(f"{SVG}desc").text
    crank = root.find(f".//{SVG}line[@data-joints='0 1']")
    ends = [float(crank.get(k)) for k in ("x1", "y1", "x2", "y2")]
    np.testing.assert_allclose(ends, positions[:2].ravel(), atol=1e-9)
    out = tmp_path / "found.dxf"
    said = ok(source, "--out", str(out))
    frame = "crank 7.5 mm (the drawing's frame)"
    assert said.strip() == f"wrote {out}: dxf, 4 joints, 3 links, {frame}"
    circles = [d for kind, _, d in dxf_parts(read_dxf(out.read_bytes())) if kind == "CIRCLE"]
    np.testing.assert_allclose([c[:2] for c in circles], positions, atol=1e-9)
    # --crank-mm scales it as before; a bare mechanism keeps the 20 mm default.
    scaled = json.loads(ok(source, "--json", "--crank-mm", "30"))
    assert scaled["frame"] == "crank" and scaled["crank_mm"] == 30
    assert [scaled["joints"][0]["x_mm"], scaled["joints"][0]["y_mm"]] == [0.0, 0.0]
    assert scaled["links"][0]["length_mm"] == pytest.approx(30)
    bare = write_json(tmp_path / "bare.json", output["results"][0]["mechanism"])
    assert json.loads(ok(bare, "--json"))["crank_mm"] == pytest.approx(20)


def test_a_mechanism_of_a_dataset(tmp_path: Path) -> None:
    root = tmp_path / "data"
    plan = GenerationPlan(seed=3, mechanisms=10, topologies_per_shard=1)
    write_shard(Store.open(str(root)), plan, plan.shards()[0])
    rows = links_ray.load(str(root), "mechanisms", reshape=True)
    row = rows.iloc[3]
    table = json.loads(
        ok(str(root), "--mechanism-id", str(row["mechanism_id"]), "--json", "--crank-mm", "10")
    )
    pos = row["positions"]
    scale = 10 / math.dist(pos[0], pos[1])
    links_found = {tuple(link["joints"]): link["length_mm"] for link in table["links"]}
    i, j = np.nonzero(np.triu(row["adjacency"]))
    expected = {(a, b): math.dist(pos[a], pos[b]) * scale for a, b in zip(i, j, strict=True)}
    assert links_found == pytest.approx(expected, abs=1e-9)
    assert [p["joint"] for p in table["ground_pivots"]] == np.flatnonzero(
        row["node_types"] == 0
    ).tolist()
    missing = links(str(root), "--mechanism-id", "999999")
    assert missing.returncode == 2
    assert missing.stderr == f"links export: error: no mechanism 999999 in {root}\n"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--crank-mm", "0"], "--crank-mm must be more than 0 and at most 100000 mm, got 0"),
        (["--crank-mm", "nan"], "--crank-mm must be more than 0 and at most 100000 mm, got nan"),
        (["--format", "svg", "--json"], "--json applies to --format table, not svg"),
        (["--path-joint", "2"], "path_joint 2 is fixed: it traces no path"),
        (["--path-joint", "x"], "--path-joint must be a joint number, auto or none, got x"),
    ],
)
def test_bad_options_end_in_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    source = write_json(tmp_path / "m.json", FOUR_BAR)
    done = links(source, *args)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"links export: error: {message}\n"


def test_bad_sources_end_in_one_line(tmp_path: Path) -> None:
    cases = {
        "missing.json": None,
        "not-json.json": "{oops",
        "no-mechanism.json": json.dumps({"points": [[0, 0]]}),
        "empty-results.json": json.dumps({"results": []}),
        "bad-mechanism.json": json.dumps({**FOUR_BAR, "node_types": [0, 1, 0, 1]}),
    }
    expected = {
        "missing.json": "cannot read a mechanism from",
        "not-json.json": "cannot read a mechanism from",
        "no-mechanism.json": "holds no mechanism: expected adjacency, node_types and positions",
        "empty-results.json": "holds no results",
        "bad-mechanism.json": "wrong crank joints: joint 1 must be the actuated joint",
    }
    for name, text in cases.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        done = links(str(tmp_path / name))
        assert done.returncode == 2, name
        assert done.stderr.count("\n") == 1 and expected[name] in done.stderr, done.stderr
    output = write_json(tmp_path / "results.json", retrieve_output())
    done = links(output, "--result", "3")
    assert done.stderr == "links export: error: --result must be from 1 to 2, got 3\n"
    locking = write_json(tmp_path / "locking.json", LOCKING_FOUR_BAR)
    done = links(locking, "--path-joint", "3")
    assert done.returncode == 2 and "mechanism locks at step" in done.stderr
    assert links(locking).returncode == 0  # without a path a locking mechanism still draws
