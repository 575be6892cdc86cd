"""`links export`: one mechanism as a drawing to build it from, or as a pylinkage script.

The mechanism comes from a JSON file (the API's `{"adjacency", "node_types", "positions"}`,
or what `links retrieve` and `links synthesize --json` print, picking result N), from stdin
(`-`), or from a dataset (`ROOT --mechanism-id ID`). It goes out in millimetres
(`engine.fabrication.drawings`): its crank `--crank-mm` long with joint 0 at the origin, or without
`--crank-mm` a result where its curve was drawn, the drawing's unit read as a millimetre (a
result's mechanism lies in the drawing's frame; any other mechanism's positions have no unit,
and its crank is made DEFAULT_CRANK_MM long). As SVG or DXF (`interop.drawings`), a table of
link lengths and ground pivots (`--json` for the table as JSON), or a Python script that
builds it with pylinkage. Or, with `--format 3d`, as printable parts
(`engine.fabrication.kit`, `interop.parts`): a folder of `bom.json`, `assembly.glb` and
`parts/*.stl`, the sizes from the options of `KIT_FLAGS`.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from links_ray.engine.fabrication import kit
from links_ray.engine.fabrication.drawings import Fabrication, fabrication
from links_ray.engine.fabrication.kit import KitOptions
from links_ray.engine.fabrication.limits import DEFAULT_CRANK_MM, as_crank_mm
from links_ray.engine.inputs import as_int
from links_ray.interop.drawings import dxf_drawing, svg_drawing

FORMATS = ("svg", "dxf", "table", "pylinkage", "3d")
#: The options of `--format 3d`: flag, `KitOptions` field, its default (mm), what it sets.
KIT_FLAGS = (
    ("--bar-width-mm", "bar_width_mm", kit.DEFAULT_BAR_WIDTH_MM, "each link's bar width"),
    ("--hole-diameter-mm", "hole_diameter_mm", kit.DEFAULT_HOLE_DIAMETER_MM, "a link's holes"),
    ("--pin-diameter-mm", "pin_diameter_mm", kit.DEFAULT_PIN_DIAMETER_MM, "each pin's diameter"),
    (
        "--spacer-diameter-mm",
        "spacer_diameter_mm",
        kit.DEFAULT_SPACER_DIAMETER_MM,
        "the spacers' outside diameter, the pins' width in the layer plan",
    ),
    (
        "--clearance-mm",
        "clearance_mm",
        kit.DEFAULT_CLEARANCE_MM,
        "the least gap between parts on a layer over the turn",
    ),
    (
        "--layer-thickness-mm",
        "layer_thickness_mm",
        kit.DEFAULT_LAYER_THICKNESS_MM,
        "each bar's thickness",
    ),
    (
        "--layer-gap-mm",
        "layer_gap_mm",
        kit.DEFAULT_LAYER_GAP_MM,
        "between layers, kept by washers",
    ),
)
#: The format an output file's suffix implies when --format is not given.
SUFFIXES = {".svg": "svg", ".dxf": "dxf", ".py": "pylinkage", ".txt": "table", ".json": "table"}


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links export` on the `links` command's subparsers."""
    command = commands.add_parser(
        "export",
        help="a mechanism as SVG, DXF or a table in millimetres, a pylinkage script, or "
        "printable 3D parts",
        description="Export one mechanism for fabrication: SVG and DXF at 1:1 in millimetres "
        "(y up), a table of its link lengths and ground pivots, a Python script that builds it "
        "with pylinkage, or (--format 3d) a folder of printable parts: a bill of materials, "
        "an STL file a part and the assembly as glTF.",
    )
    command.add_argument(
        "source",
        help="a JSON file (a mechanism, or the output of links retrieve / links synthesize "
        "--json), - for stdin, or with --mechanism-id a dataset root (a folder or s3://...)",
    )
    command.add_argument(
        "--mechanism-id",
        type=int,
        default=None,
        metavar="ID",
        help="the mechanism of dataset SOURCE to export",
    )
    command.add_argument(
        "--result",
        type=int,
        default=1,
        metavar="N",
        help="which result of a retrieve or synthesize output to export, from 1",
    )
    command.add_argument(
        "--format",
        choices=FORMATS,
        default=None,
        help="what to write (default: from the --out suffix, .svg .dxf .py .txt .json; else table)",
    )
    command.add_argument(
        "--crank-mm",
        type=float,
        default=None,
        metavar="MM",
        help="the crank's length (joint 0 to joint 1) in millimetres: sets the scale, joint 0 "
        "at the origin (default: a result of links retrieve or synthesize keeps the drawing's "
        f"frame, its unit read as a millimetre; any other mechanism a {DEFAULT_CRANK_MM:g} mm "
        "crank)",
    )
    command.add_argument(
        "--path-joint",
        default="auto",
        metavar="J",
        help="draw the path joint J traces over a crank turn; none for no path (default "
        "auto: a result's own joint, else none)",
    )
    command.add_argument(
        "--out",
        default=None,
        metavar="FILE",
        help="output file (default: stdout); with --format 3d a folder, new, empty or holding "
        "an earlier kit",
    )
    command.add_argument(
        "--json", action="store_true", help="with --format table: the table as JSON"
    )
    for flag, _, default, what in KIT_FLAGS:
        command.add_argument(
            flag,
            type=float,
            default=None,
            metavar="MM",
            help=f"with --format 3d: {what} (default {default:g})",
        )
    command.add_argument(
        "--ground-on-base",
        action="store_true",
        help="with --format 3d: fixed joints' pins stand on a base plate under the layers",
    )
    command.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links export`: write the mechanism in the format asked for; ValueError if it cannot."""
    chosen = args.format
    if chosen is None:
        suffix = Path(args.out).suffix.lower() if args.out else ""
        chosen = SUFFIXES.get(suffix, "table")
    if args.json and chosen != "table":
        raise ValueError(f"--json applies to --format table, not {chosen}")
    given = [flag for flag, field, _, _ in KIT_FLAGS if getattr(args, field) is not None]
    given += ["--ground-on-base"] if args.ground_on_base else []
    if chosen != "3d" and given:
        raise ValueError(f"{given[0]} applies to --format 3d, not {chosen}")
    if chosen == "3d" and (args.out is None or args.path_joint != "auto"):
        raise ValueError(
            "--format 3d writes a folder: give it with --out DIR"
            if args.out is None
            else "--path-joint applies to the drawings, not --format 3d"
        )
    if args.crank_mm is not None:
        as_crank_mm(args.crank_mm, "--crank-mm")  # named as the user typed it, before reading
    source = read_mechanism(args.source, args.mechanism_id, args.result)
    if chosen == "3d":
        write_kit(args, source)
        return
    mechanism = source.mechanism
    drawing = fabrication(
        mechanism["adjacency"],
        mechanism["node_types"],
        mechanism["positions"],
        crank_mm=source.crank_mm(args.crank_mm),
        path_joint=_path_joint(args.path_joint, source.own_joint),
    )
    text = render(drawing, mechanism, chosen, args.json)
    if args.out is None:
        sys.stdout.write(text)
        return
    Path(args.out).write_text(text, encoding="utf-8")
    frame = " (the drawing's frame)" if drawing.frame == "drawing" else ""
    print(
        f"wrote {args.out}: {chosen}, {len(drawing.node_types)} joints, "
        f"{len(drawing.links)} links, crank {drawing.crank_mm:g} mm{frame}"
    )


def write_kit(args: argparse.Namespace, source: Source) -> None:
    """`--format 3d`: the mechanism's printable parts written into the folder `--out`, and a
    line saying what was written; ValueError (with the flags named as typed) if it cannot be
    built."""
    from links_ray.interop.parts import export_kit  # loads the 3D libraries

    fields = {field: getattr(args, field) for _, field, _, _ in KIT_FLAGS}
    try:
        options = KitOptions(
            crank_mm=source.crank_mm(args.crank_mm),
            ground_on_base=args.ground_on_base,
            **{field: value for field, value in fields.items() if value is not None},
        )
        mechanism = source.mechanism
        bom = export_kit(
            mechanism["adjacency"],
            mechanism["node_types"],
            mechanism["positions"],
            args.out,
            options,
        )
    except (ValueError, ImportError) as exc:  # ImportError: the `build` extra is missing
        message = str(exc)
        for flag, field, _, _ in (*KIT_FLAGS, ("--crank-mm", "crank_mm", 0, "")):
            message = re.sub(rf"\b{field}\b", flag, message)
        raise ValueError(message) from None
    frame = " (the drawing's frame)" if bom["frame"] == "drawing" else ""
    print(
        f"wrote {args.out}: 3d, {len(bom['joints'])} joints, {len(bom['links'])} links, "
        f"{bom['layers']} layers ({bom['status']}), {len(bom['parts'])} parts, crank "
        f"{bom['crank_mm']:g} mm{frame}"
    )


def render(drawing: Fabrication, mechanism: dict[str, Any], chosen: str, as_json: bool) -> str:
    """The file's text in format `chosen`."""
    if chosen == "svg":
        return svg_drawing(drawing)
    if chosen == "dxf":
        return dxf_drawing(drawing)
    if chosen == "pylinkage":
        from links_ray.interop.pylinkage import pylinkage_script  # text only: no pylinkage

        return pylinkage_script(
            mechanism["adjacency"],
            mechanism["node_types"],
            drawing.joints_mm,
            decimals=9,  # to the nanometre, as the drawings
            title=f"a links-ray mechanism (millimetres, crank {drawing.crank_mm:g} mm)",
        )
    return json.dumps(drawing.table(), indent=1) + "\n" if as_json else drawing.table_text()


def _path_joint(option: str, own_joint: int | None) -> int | None:
    if option == "auto":
        return own_joint
    if option == "none":
        return None
    try:
        return int(option)
    except ValueError:
        raise ValueError(
            f"--path-joint must be a joint number, auto or none, got {option}"
        ) from None


@dataclass(frozen=True)
class Source:
    """The mechanism to export (`adjacency`, `node_types`, `positions`), its own path joint (a
    result's `mechanism_joint`, else None), and whether it is a result's: placed in the frame
    of the curve it was found for."""

    mechanism: dict[str, Any]
    own_joint: int | None
    drawn: bool

    def crank_mm(self, given: float | None) -> float | None:
        """The crank length to scale to: the one given, else None (the drawing's frame) for a
        result and DEFAULT_CRANK_MM for a mechanism whose positions have no unit."""
        if given is not None:
            return given
        return None if self.drawn else DEFAULT_CRANK_MM


def read_mechanism(source: str, mechanism_id: int | None, result: int) -> Source:
    """The mechanism to export, from a JSON file, stdin (`-`) or a dataset root with
    `mechanism_id`."""
    if mechanism_id is not None:
        return Source(dataset_mechanism(source, mechanism_id), None, drawn=False)
    where = "stdin" if source == "-" else source
    try:
        text = sys.stdin.read() if source == "-" else Path(source).read_text()
        data = json.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read a mechanism from {where}: {exc}") from None
    return mechanism_in(data, result, where)


def mechanism_in(data: object, result: int, where: str) -> Source:
    """The mechanism in parsed JSON: a mechanism itself, a result holding one, or result
    `result` (from 1) of `{"results": [...]}` or a list of results."""
    fields = ("adjacency", "node_types", "positions")
    if isinstance(data, dict) and all(name in data for name in fields):
        return Source({name: data[name] for name in fields}, None, drawn=False)
    if isinstance(data, dict) and "results" in data:
        data = data["results"]
    if isinstance(data, list) and all(isinstance(r, dict) for r in data):
        if not data:
            raise ValueError(f"{where} holds no results")
        as_int("--result", result, 1, len(data))
        data = data[result - 1]
    if isinstance(data, dict) and isinstance(data.get("mechanism"), dict):
        mechanism = data["mechanism"]
        if all(name in mechanism for name in fields):
            joint = data.get("mechanism_joint")
            return Source({name: mechanism[name] for name in fields}, joint, drawn=True)
    raise ValueError(
        f"{where} holds no mechanism: expected adjacency, node_types and positions, or the "
        "results of links retrieve or links synthesize --json"
    )


def dataset_mechanism(root: str, mechanism_id: int) -> dict[str, Any]:
    """The mechanism `mechanism_id` of the dataset at `root`, from its committed rows."""
    import numpy as np
    import pyarrow.dataset as pads

    from links_ray.data.dataset import open_table

    table = open_table(root, "mechanisms").to_table(
        columns=["adjacency", "node_types", "positions"],
        filter=pads.field("mechanism_id") == mechanism_id,
    )
    if table.num_rows == 0:
        raise ValueError(f"no mechanism {mechanism_id} in {root}")
    row = table.slice(0, 1).to_pylist()[0]
    n = len(row["node_types"])
    return {
        "adjacency": np.asarray(row["adjacency"]).reshape(n, n),
        "node_types": np.asarray(row["node_types"]),
        "positions": np.asarray(row["positions"], dtype=np.float64).reshape(n, 2),
    }
