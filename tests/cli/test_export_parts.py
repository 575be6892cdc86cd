"""`links export FILE --format 3d --out DIR` (cli/export.py): a folder of printable parts, in the
drawing's frame for a result and scaled with --crank-mm; one-line errors for a bad file, bad
options and a mechanism no stacking of layers can build.

Run as the user runs it, in a subprocess. The parts themselves are tested in
tests/interop/test_parts.py.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests.cli.test_export_mechanism import links, ok, synthesis_output, write_json
from tests.interop.test_parts import UNBUILDABLE
from tests.support.needs import need_module

need_module("trimesh", "pip install 'links-ray[build]' (the test extra)")


def test_a_result_keeps_its_frame_and_the_crank_length_scales_it(tmp_path: Path) -> None:
    output = synthesis_output()
    source = write_json(tmp_path / "found.json", output)
    positions = np.asarray(output["results"][0]["mechanism"]["positions"])
    out = tmp_path / "kept"
    said = ok(source, "--format", "3d", "--out", str(out), "--bar-width-mm", "7")
    bom = json.loads((out / "bom.json").read_text())
    assert said.strip() == (
        f"wrote {out}: 3d, 4 joints, 3 links, {bom['layers']} layers ({bom['status']}), "
        f"{len(bom['parts'])} parts, crank 7.5 mm (the drawing's frame)"
    )
    assert (bom["unit"], bom["frame"], bom["mm_per_unit"]) == ("mm", "drawing", 1.0)
    kept = [[joint["x_mm"], joint["y_mm"]] for joint in bom["joints"]]
    np.testing.assert_array_equal(kept, positions)
    assert bom["bar_width_mm"] == 7 and bom["clearance_mm"] == 1
    assert sorted(str(path.relative_to(out)) for path in out.rglob("*.*")) == sorted(
        ["bom.json", "assembly.glb", *bom["parts"]]
    )
    scaled = tmp_path / "scaled"
    ok(source, "--format", "3d", "--out", str(scaled), "--crank-mm", "30", "--ground-on-base")
    bom = json.loads((scaled / "bom.json").read_text())
    assert (bom["frame"], bom["crank_mm"], bom["ground_on_base"]) == ("crank", 30, True)
    assert bom["joints"][0]["x_mm"] == bom["joints"][0]["y_mm"] == 0
    crank = next(link for link in bom["links"] if link["joints"] == [0, 1])
    assert crank["length_mm"] == pytest.approx(30)
    assert bom["mm_per_unit"] == pytest.approx(30 / math.dist(positions[0], positions[1]))
    # The same folder again: the earlier build is replaced.
    ok(source, "--format", "3d", "--out", str(scaled), "--crank-mm", "40")
    assert json.loads((scaled / "bom.json").read_text())["crank_mm"] == 40


def test_errors_end_in_one_line(tmp_path: Path) -> None:
    unbuildable = {name: np.asarray(value).tolist() for name, value in UNBUILDABLE.items()}
    source = write_json(tmp_path / "m.json", unbuildable)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    cases = [
        ([str(tmp_path / "missing.json"), "--out", "x"], "cannot read a mechanism from"),
        ([source, "--out", str(tmp_path / "none")], "no layer plan keeps every pin clear"),
        ([source], "--format 3d writes a folder: give it with --out DIR"),
        ([source, "--out", "x", "--path-joint", "3"], "--path-joint applies to the drawings"),
        (
            [source, "--out", "x", "--hole-diameter-mm", "2.5"],
            "--pin-diameter-mm must be less than --hole-diameter-mm (the pin turns in the hole)",
        ),
        ([source, "--out", "x", "--layer-gap-mm", "-1"], "--layer-gap-mm must be from 0"),
        ([source, "--out", str(tmp_path / "full")], "holds files but no earlier kit"),
    ]
    for args, words in cases:
        done = links(args[0], "--format", "3d", *args[1:])
        assert done.returncode == 2 and done.stdout == "", args
        assert done.stderr.count("\n") == 1 and words in done.stderr, done.stderr
    assert not (tmp_path / "none").exists() and not Path("x").exists()
    done = links(source, "--format", "svg", "--ground-on-base")
    assert done.stderr == "links export: error: --ground-on-base applies to --format 3d, not svg\n"
