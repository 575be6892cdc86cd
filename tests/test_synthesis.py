"""Synthesis (engine.synthesis) over the Serve tests' small dataset, against independent truth.

* A retrieved mechanism, unrefined, measures the retrieval's own chamfer.
* Every synthesized mechanism, re-simulated with `links_ray.simulate`, traces a path whose
  chamfer to the drawing is the one reported, no worse than where it started, and is valid:
  it turns at 2,000 steps, keeps its branches and its transmission margin.
* A partial stroke gets the interval of crank steps that traces it.
* The CLI and the HTTP API answer, and refuse bad input in one line / a 4xx JSON error.
"""

from __future__ import annotations

import http.client
import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from serving import Client, hand_drawn
from test_cli import links
from test_refine import assert_valid

import links_ray
from links_ray.engine.inputs import MAX_SYNTHESIS_SECONDS, MIN_POINTS
from links_ray.engine.paths import chamfer, longest_chord
from links_ray.engine.synthesis import CANDIDATES, fit, refine_retrieved, synthesize
from links_ray.search.index import RetrievalIndex


def chord(points: np.ndarray) -> float:
    i, j = longest_chord(points)
    return float(np.linalg.norm(points[j] - points[i]))


def traced(result: dict, steps: int = 200) -> np.ndarray:
    """The path of a result's `mechanism_joint`, simulated afresh."""
    mechanism = result["mechanism"]
    return links_ray.simulate(
        mechanism["adjacency"], mechanism["node_types"], mechanism["positions"], steps
    )[result["mechanism_joint"]]


def test_an_unrefined_retrieval_measures_the_retrievals_chamfer(
    reference: RetrievalIndex, queries: list
) -> None:
    for query in queries:
        for result in reference.retrieve(query, k=3):
            mechanism = result["mechanism"]
            value, interval = fit(
                query,
                mechanism["positions"],
                mechanism["adjacency"],
                mechanism["node_types"],
                result["mechanism_joint"],
            )
            assert interval is None
            # Stored paths are float32 (normalized: coordinates near 1, so each is off by up
            # to about 3e-8); the mechanism placed in the query's frame traces in float64.
            assert value == pytest.approx(result["chamfer"], rel=0, abs=5e-7)


def test_synthesis_refines_and_reports_what_it_traces(
    reference: RetrievalIndex, queries: list
) -> None:
    improved = 0
    for query in [queries[0], *hand_drawn()[:2]]:
        start = time.perf_counter()
        results = synthesize(reference, query, k=3, seconds=1.0)
        took = time.perf_counter() - start
        assert took < 2.5  # the budget, plus one iteration and the answer's simulation
        assert len(results) == 3
        chamfers = [r["chamfer"] for r in results]
        assert chamfers == sorted(chamfers)
        assert len({r["path_id"] for r in results}) == 3
        retrieved = {r["path_id"]: r for r in reference.retrieve(query, CANDIDATES)}
        for result in results:
            path = traced(result)
            assert result["chamfer"] == pytest.approx(
                chamfer(query, path) / chord(query), rel=1e-12
            )
            np.testing.assert_array_equal(np.array(result["path"]), path)
            assert result["interval"] is None
            start_from = retrieved[result["path_id"]]
            assert start_from["mechanism_id"] == result["mechanism_id"]
            assert result["retrieved_chamfer"] == pytest.approx(
                start_from["chamfer"], rel=0, abs=5e-7
            )
            assert result["chamfer"] <= result["retrieved_chamfer"] + 1e-12
            improved += result["chamfer"] < 0.9 * result["retrieved_chamfer"]
            mechanism = start_from["mechanism"]
            assert mechanism["adjacency"] == result["mechanism"]["adjacency"]
            assert_valid(
                np.array(mechanism["adjacency"]),
                np.array(mechanism["node_types"]),
                np.array(mechanism["positions"]),
                np.array(result["mechanism"]["positions"]),
                3.0,
            )
        # The best refined beats the best retrieved: refinement found something.
        assert results[0]["chamfer"] < min(r["chamfer"] for r in retrieved.values())
    assert improved >= 6


def test_a_partial_stroke_gets_its_crank_interval(reference: RetrievalIndex, curated: Any) -> None:
    """A third of a stored path, turned and moved: some run of steps traces it."""
    path = curated.points.iloc[7].astype(np.float64)
    stroke = path[40:107] @ np.array([[0.6, -0.8], [0.8, 0.6]]) * 3.0 + [5.0, -2.0]
    results = synthesize(reference, stroke, k=2, seconds=1.0, partial=True)
    assert len(results) == 2
    for result in results:
        interval = result["interval"]
        assert MIN_POINTS <= interval["steps"] <= 200
        assert interval["start_deg"] == pytest.approx(360 * interval["start_step"] / 200)
        assert interval["sweep_deg"] == pytest.approx(360 * (interval["steps"] - 1) / 200)
        run = traced(result)[(interval["start_step"] + np.arange(interval["steps"])) % 200]
        assert result["chamfer"] == pytest.approx(chamfer(stroke, run) / chord(stroke), rel=1e-12)
        assert result["chamfer"] <= result["retrieved_chamfer"] + 1e-12
        # The run is the best of all runs, the whole turn among them.
        whole = chamfer(stroke, traced(result)) / chord(stroke)
        assert result["chamfer"] <= whole + 1e-12


def test_no_time_left_returns_the_retrieved_mechanisms_measured(
    reference: RetrievalIndex, queries: list
) -> None:
    """With the budget spent before refinement starts, the answers are the retrieved
    mechanisms at least once refined (each pass runs one iteration at least)."""
    query = queries[1]
    retrieved = reference.retrieve(query, 8)
    results = refine_retrieved(query, retrieved, 3, 0.001, started=time.perf_counter() - 1.0)
    for result in results:
        assert result["chamfer"] <= result["retrieved_chamfer"] + 1e-12
        assert result["chamfer"] == pytest.approx(
            chamfer(query, traced(result)) / chord(query), rel=1e-12
        )


@pytest.mark.parametrize(
    ("args", "words"),
    [
        ({"k": 0}, "k must be from 1 to 100"),
        ({"seconds": 0}, "seconds must be more than 0"),
        ({"seconds": MAX_SYNTHESIS_SECONDS + 1}, f"at most {MAX_SYNTHESIS_SECONDS:g}"),
        ({"seconds": "3"}, "seconds must be a number"),
        ({"partial": "yes"}, "partial must be true or false"),
        ({"points": [[0, 0], [1, 1]]}, "points must hold 3 to 10000 pairs"),
        ({"points": [[0, 0], [0, 0], [0, 0]]}, "all the same point"),
    ],
)
def test_bad_input_raises_value_error(reference: RetrievalIndex, args: dict, words: str) -> None:
    call = {"points": hand_drawn()[0], **args}
    with pytest.raises(ValueError, match=words):
        synthesize(reference, **call)


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
    for bad, message in (
        (["--seconds", "31"], "seconds must be more than 0 and at most 30, got 31"),
        (["-k", "101"], "k must be from 1 to 100, got 101"),
    ):
        done = links("synthesize", dataset, "--points", str(points), *bad)
        assert done.returncode == 2
        assert done.stderr == f"links synthesize: error: {message}\n"
    done = links("synthesize", dataset, "--points", str(tmp_path / "missing.json"))
    assert done.returncode == 2
    assert done.stderr.startswith("links synthesize: error: cannot read points from")
    assert done.stderr.count("\n") == 1


# -- the HTTP API ----------------------------------------------------------------------------


def test_http_synthesize(client: Client) -> None:
    curve = hand_drawn()[0].tolist()
    status, data = client.post("/api/synthesize", {"points": curve, "k": 2, "seconds": 1})
    assert status == 200, data
    assert len(data["results"]) == 2 and data["took_ms"] < 2500
    for result in data["results"]:
        assert result["chamfer"] <= result["retrieved_chamfer"] + 1e-12
        path = traced(result)
        assert result["chamfer"] == pytest.approx(chamfer(curve, path) / chord(np.array(curve)))
    stroke = curve[:50]
    status, data = client.post(
        "/api/synthesize", {"points": stroke, "seconds": 0.5, "partial": True}
    )
    assert status == 200, data
    assert len(data["results"]) == 3 and data["results"][0]["interval"]["steps"] >= MIN_POINTS


def test_http_synthesize_streams_its_progress(client: Client) -> None:
    """With "stream": the best so far as it falls, each a real mechanism tracing what it says
    (re-simulated), then the answer; the best reported is never better than the answer."""
    curve = hand_drawn()[2].tolist()
    conn = http.client.HTTPConnection("127.0.0.1", client.port, timeout=60)
    body = json.dumps({"points": curve, "k": 2, "seconds": 1.5, "stream": True})
    conn.request("POST", "/api/synthesize", body, {"Content-Type": "application/json"})
    response = conn.getresponse()
    assert response.status == 200
    assert response.getheader("Content-Type").startswith("application/x-ndjson")
    lines = [json.loads(line) for line in response.read().splitlines()]
    conn.close()
    *reports, answer = lines
    assert len(reports) >= 2 and all(set(line) == {"progress"} for line in reports)
    progress = [line["progress"] for line in reports]
    chamfers = [best["chamfer"] for best in progress]
    assert chamfers == sorted(chamfers, reverse=True) and len(set(chamfers)) == len(chamfers)
    assert progress[0]["chamfer"] == progress[0]["retrieved_chamfer"]  # the retrieved start
    elapsed = [best["elapsed_ms"] for best in progress]
    # Reported as they came, all before the answer (a last round may end past the budget).
    assert elapsed == sorted(elapsed) and elapsed[-1] <= answer["took_ms"]
    for best in (progress[0], progress[-1]):
        trajectories = np.array(best["trajectories"])
        mechanism = best["mechanism"]
        np.testing.assert_array_equal(trajectories, links_ray.simulate(**mechanism, steps=200))
        np.testing.assert_array_equal(trajectories[best["mechanism_joint"]], best["path"])
        assert best["chamfer"] == pytest.approx(
            chamfer(curve, best["path"]) / chord(np.array(curve))
        )
    assert len(answer["results"]) == 2 and answer["took_ms"] < 2500
    assert answer["results"][0]["chamfer"] <= chamfers[-1]
    assert "trajectories" not in answer["results"][0]


def test_http_synthesize_stream_flag_is_checked(client: Client) -> None:
    got, data = client.post("/api/synthesize", {"points": hand_drawn()[0].tolist(), "stream": 1})
    assert got == 400 and data["error"] == "stream must be true or false, got 1"


@pytest.mark.parametrize(
    ("body", "status", "words"),
    [
        ({"k": 2}, 400, "missing field 'points'"),
        ({"points": "abc"}, 400, "points must be an array of [x, y] pairs"),
        ({"points": [[0, 0], [1, 1]]}, 400, "points must hold 3 to 10000 pairs"),
        ({"points": [[0, 0], [1, 1], [2, 0]], "k": 0}, 400, "k must be from 1 to 100"),
        ({"points": [[0, 0], [1, 1], [2, 0]], "seconds": 31}, 400, "at most 30"),
        ({"points": [[0, 0], [1, 1], [2, 0]], "seconds": True}, 400, "seconds must be a number"),
        ({"points": [[0, 0], [1, 1], [2, 0]], "partial": 1}, 400, "partial must be true or false"),
        ([1, 2], 400, "the body must be a JSON object"),
    ],
)
def test_http_synthesize_refuses_bad_requests(
    client: Client, body: Any, status: int, words: str
) -> None:
    got, data = client.post("/api/synthesize", body)
    assert got == status, data
    assert words in data["error"]
    got, _, data = client.request("POST", "/api/synthesize", b"{not json")
    assert got == 400 and "not valid JSON" in data["error"]


def test_health_is_answered_during_syntheses(client: Client) -> None:
    """Two syntheses of 3 s hold the replica (a third is refused 503); health answers at once."""
    curve = hand_drawn()[4].tolist()
    answers: list[int] = []

    def run() -> None:
        answers.append(client.post("/api/synthesize", {"points": curve, "seconds": 3})[0])

    threads = [threading.Thread(target=run) for _ in range(2)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)
    status, _ = client.post("/api/synthesize", {"points": curve, "seconds": 3})
    assert status == 503
    waits = []
    for _ in range(5):
        start = time.perf_counter()
        assert client.get("/api/health")[0] == 200
        waits.append(time.perf_counter() - start)
        time.sleep(0.1)
    for thread in threads:
        thread.join()
    assert answers == [200, 200]
    assert max(waits) < 0.5, waits


#: A refined mechanism the synthesis bench once answered with, which `simulate` then refused:
#: one of its dyads ends 0.016 degrees from its dead centre (retrieved at about twice that,
#: so its margin was half its own), grazing it along a stretch of the turn. Between 200 steps
#: the check cannot prove it turns; at 2,000 it took 79 s to, and is now refused within its
#: split budget (test_turning).
HAIR_EDGES = [(0, 1), (1, 3), (1, 4), (1, 7), (2, 3), (2, 5), (2, 9), (3, 4), (3, 5), (3, 6)]
HAIR_EDGES += [(3, 7), (4, 6), (5, 11), (6, 8), (6, 9), (7, 8), (8, 10), (9, 10), (10, 11)]
HAIR_POSITIONS = [
    [-35.603034290353754, -7.052549970023862],
    [-38.366472614147156, -5.473627347042383],
    [-16.328271862677738, 5.335569973367106],
    [-28.4971503147137, 27.7582880146957],
    [-36.79249147765405, -31.262020218311424],
    [-22.23388843814021, -39.88672420825982],
    [-14.36274742427628, -14.238581594873715],
    [-31.549856370887774, 17.479231913824787],
    [-20.576711103535292, -2.776252436391257],
    [-44.227437894545176, -1.902373368040407],
    [-61.04100999536202, -21.780127808254008],
    [-40.041102893462586, -13.882951763971386],
]


def test_a_refinement_simulate_cannot_trace_at_200_steps_is_not_kept() -> None:
    """Every result is simulated at 200 steps: a refinement `simulate` cannot trace there is
    refused, and the candidate keeps what it had."""
    from links_ray.engine import synthesis
    from links_ray.engine.mechanism import LockingError, analyze_topology
    from links_ray.engine.refine import Refinement

    adjacency = np.zeros((12, 12), dtype=int)
    for i, j in HAIR_EDGES:
        adjacency[i, j] = adjacency[j, i] = 1
    node_types = np.array([0, 2, 0] + [1] * 9)
    positions = np.array(HAIR_POSITIONS)
    topology = analyze_topology(adjacency, node_types)
    with pytest.raises(LockingError):
        links_ray.simulate(adjacency, node_types, positions, 200)

    before = positions + 0.5  # any mechanism: only the refinement is judged here
    candidate = synthesis._Candidate({}, topology, 11, before, before, 0.05, 0.05, None)
    refined = Refinement(positions, 0.05, 0.01, None, 10, 10, 0.016)
    assert not synthesis._keep(candidate, refined, 100)
    assert candidate.positions is before and candidate.chamfer == 0.05


def test_synthesis_figure_draws_each_curve(reference: RetrievalIndex, tmp_path: Path) -> None:
    """`links bench synthesize --figure`'s picture: a panel per curve, written as a PNG."""
    import matplotlib.pyplot as pyplot

    from links_ray.cli.figures import write_synthesis_figure

    entries = []
    for name, points in (("ellipse", hand_drawn()[0]), ("kidney", hand_drawn()[4])):
        best = synthesize(reference, points, k=1, seconds=0.3)[0]
        first = reference.retrieve(points, 1)[0]
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
