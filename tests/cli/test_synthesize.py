"""`links synthesize` over the Serve tests' dataset: its table, its JSON, counted work that
repeats, bad options refused in one line; and `links bench synthesize --figure`'s picture.
The engine's own tests of synthesis are tests/engine/synthesis/test_synthesis.py."""

from __future__ import annotations

import json
from pathlib import Path

from links_ray.engine.synthesis.pipeline import synthesize
from links_ray.search.index import RetrievalIndex
from tests.engine.synthesis.test_synthesis import traced
from tests.support.cli import links
from tests.support.serving import hand_drawn

# -- the command line ------------------------------------------------------------------------


def test_links_synthesize(dataset: str, tmp_path: Path) -> None:
    points = tmp_path / "curve.json"
    points.write_text(json.dumps({"points": hand_drawn()[0].tolist()}))
    done = links("synthesize", dataset, "--points", str(points), "-k", "2", "--seconds", "1")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("2 mechanisms in ")
    lines = done.stdout.splitlines()  # a title, a header, two ranked rows, a footnote
    assert len(lines) == 5 and [line.split()[0] for line in lines[2:4]] == ["1", "2"]
    done = links(
        "synthesize", dataset, "--points", str(points), "-k", "2", "--seconds", "1", "--json"
    )
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout)["results"]
    assert len(results) == 2 and results[0]["chamfer"] <= results[0]["retrieved_chamfer"]
    fixed = ["-k", "2", "--seed", "4", "--iterations", "200", "--json"]
    done = links("synthesize", dataset, "--points", str(points), *fixed)
    assert done.returncode == 0, done.stderr
    again = links("synthesize", dataset, "--points", str(points), *fixed)
    assert again.returncode == 0, again.stderr
    answer = json.loads(done.stdout)["results"]
    assert len(answer) == 2 and answer == json.loads(again.stdout)["results"]
    for bad, message in (
        (["--seconds", "31"], "seconds must be more than 0 and at most 30, got 31"),
        (["-k", "101"], "k must be from 1 to 100, got 101"),
        (
            ["--seconds", "1", "--iterations", "5"],
            "give seconds or iterations, not both: iterations fix the work whatever the time",
        ),
    ):
        done = links("synthesize", dataset, "--points", str(points), *bad)
        assert done.returncode == 2
        assert done.stderr == f"links synthesize: error: {message}\n"
    done = links("synthesize", dataset, "--points", str(tmp_path / "missing.json"))
    assert done.returncode == 2
    assert done.stderr.startswith("links synthesize: error: cannot read points from")
    assert done.stderr.count("\n") == 1


def test_synthesis_figure_draws_each_curve(dataset_index: RetrievalIndex, tmp_path: Path) -> None:
    """`links bench synthesize --figure`'s picture: a panel per curve, written as a PNG."""
    import matplotlib.pyplot as pyplot

    from links_ray.cli.figures import write_synthesis_figure

    entries = []
    for name, points in (("ellipse", hand_drawn()[0]), ("kidney", hand_drawn()[4])):
        best = synthesize(dataset_index, points, k=1, seconds=0.3)[0]
        first = dataset_index.retrieve(points, 1)[0]
        entries.append(
            {
                "curve": name,
                "points": points,
                "retrieved_path": traced(first),
                "retrieved": first["chamfer"],
                "refined": best["chamfer"],
                "result": best,
            }
        )
    written = write_synthesis_figure(tmp_path / "synthesis.png", entries)
    image = pyplot.imread(written)
    assert image.shape[0] > 200 and image.shape[1] > 4 * 200  # one row of four panels
    # The two drawn panels hold ink; the two empty ones are blank.
    quarter = image.shape[1] // 4
    ink = [float((image[:, i * quarter : (i + 1) * quarter, :3] < 0.9).mean()) for i in range(4)]
    assert ink[0] > 0.01 and ink[1] > 0.01 and ink[2] == ink[3] == 0.0


def test_a_bench_row_reports_its_floor_and_its_front_as_kits(
    dataset_index: RetrievalIndex,
) -> None:
    """`links bench synthesize --front --min-transmission`'s row: its answer keeps the floor
    asked, and each answer of the front is stated with the layers its own kit plan finds (the
    same answers again, as counted work repeats)."""
    import numpy as np

    from links_ray.bench.synthesis import bench_row
    from links_ray.bench.synthesis_report import front_layers
    from links_ray.engine.synthesis.kit_layers import kit_layer_count

    points = hand_drawn()[0]
    row, _ = bench_row(
        dataset_index, "ellipse", points, iterations=200, min_transmission=10.0, front=True
    )
    assert row["transmission_deg"] >= 10.0 - 1e-4
    again = synthesize(
        dataset_index, points, front=True, min_transmission=10.0, seed=0, iterations=200
    )
    assert [answer["chamfer"] for answer in row["front"]] == [r["chamfer"] for r in again]
    assert row["refined"] == min(r["chamfer"] for r in again)
    for answer, result in zip(row["front"], again, strict=True):
        assert answer["transmission_deg"] >= 10.0 - 1e-4
        mechanism = result["mechanism"]
        assert answer["layers"] == kit_layer_count(
            *(np.array(mechanism[key]) for key in ("adjacency", "node_types", "positions"))
        )
    summary = front_layers([row])
    assert summary["answers"] == len(again)
    assert 0.0 <= summary["no_plan"] <= 1.0 and row["layer_seconds"] > 0
