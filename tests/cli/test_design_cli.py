"""`links synthesize` with constraints, timing, a front and `--max-joints`; bad constraint
files refused in one line. The engine's own tests of constraints are
tests/engine/synthesis/test_design.py."""

from __future__ import annotations

import json
from pathlib import Path

from links_ray.interop.curve_limits import MAX_CURVE_FILE_BYTES
from tests.engine.synthesis.test_design import misses
from tests.support.cli import links
from tests.support.serving import hand_drawn

# -- the CLI ---------------------------------------------------------------------------


def test_links_synthesize_with_constraints_and_timing(dataset: str, tmp_path: Path) -> None:
    drawn = hand_drawn()[0]
    points = tmp_path / "curve.json"
    points.write_text(json.dumps(drawn.tolist()))
    low, high = drawn.min(axis=0), drawn.max(axis=0)
    span = float((high - low).max())
    given = {"pivots": [*(low - 0.1 * span), *(high + 0.1 * span)]}
    constraints = tmp_path / "constraints.json"
    constraints.write_text(json.dumps(given))
    common = ["--points", str(points), "--iterations", "300", "--json"]
    done = links("synthesize", dataset, *common, "--constraints", str(constraints), "--timing")
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout)["results"]
    assert results
    for result in results:
        assert max(misses(result, given).values()) == 0.0
        assert 0 < result["timed_error"]
    done = links("synthesize", dataset, *common, "--front", "--max-joints", "12")
    assert done.returncode == 0, done.stderr
    joints = [r["n_joints"] for r in json.loads(done.stdout)["results"]]
    assert joints and joints == sorted(set(joints)) and joints[-1] <= 12
    constraints.write_text(json.dumps({"pivot": [0, 0, 1, 1]}))
    done = links("synthesize", dataset, "--points", str(points), "--constraints", str(constraints))
    assert done.returncode == 2
    assert done.stderr.startswith("links synthesize: error: unknown constraint 'pivot'")
    assert done.stderr.count("\n") == 1
    # A file that is no JSON, or too large to be a designer's, is named and refused.
    for text, said in (
        ("{pivots", "not JSON"),
        (" " * MAX_CURVE_FILE_BYTES + "{}", f"larger than {MAX_CURVE_FILE_BYTES:,} bytes"),
    ):
        constraints.write_text(text)
        done = links(
            "synthesize", dataset, "--points", str(points), "--constraints", str(constraints)
        )
        assert done.returncode == 2
        assert done.stderr.startswith(
            f"links synthesize: error: --constraints {constraints}: {said}"
        )
        assert done.stderr.count("\n") == 1
