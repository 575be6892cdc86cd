"""Drawing files that no input can freeze, crash or exhaust (links_ray.interop.curve_files and
curve_worker): each input here is one that once held a reader for seconds to minutes, took
gigabytes, or failed with the wrong error. The readers bound it before parsing, and the
reader processes of `curve_worker` hold what slips past to their time and memory limits.

Inputs read through a reader process are given its real time limit (CURVE_READ_SECONDS): an
input that overran it before the bounds is now read, or refused naming its limit, well
within it. Nothing else here is timed."""

from __future__ import annotations

import io
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import ezdxf
import numpy as np
import pytest

from links_ray.interop.curve_files import read_curve, read_curve_text, read_points
from links_ray.interop.curve_limits import (
    CURVE_READER_NICENESS,
    MAX_CURVE_SEGMENTS,
    MAX_DXF_ENTITIES,
    MAX_SPLINE_FIT_POINTS,
    MAX_SVG_ELEMENTS,
)
from links_ray.interop.curve_worker import (
    CurveFileTooCostly,
    CurveReaders,
    CurveReadersBusy,
    read_curve_isolated,
)
from links_ray.interop.dxf_curves import read_dxf
from links_ray.interop.outlines import FLAT_POINTS, CurveFileTooLarge
from links_ray.serve.http.admission import RETRIEVAL_NICENESS

SVG = '<svg xmlns="http://www.w3.org/2000/svg">{}</svg>'
PLAIN = '<path id="wing" d="M 0 0 C 10 20 30 -10 40 5 L 35 -12 Q 20 -25 4 -6 Z"/>'
#: A drawing at the limits, real work for a reader: about a second here, a tenth on any machine.
HEAVY = SVG.format('<path d="M0 0 L1 1 L2 0"/>' * (MAX_SVG_ELEMENTS - 1))
TINY = "0,0\n1,1\n2,0\n"


def dxf_text(build: Callable[[Any], object]) -> str:
    """The DXF `build(modelspace)` draws, as text."""
    doc = ezdxf.new()
    build(doc.modelspace())
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue()


def use_bomb(levels: int, size: int | None = None) -> str:
    """A path, then `levels` groups each of ten `<use>` of the one before: 10^levels paths
    once expanded; padded with a comment to `size` bytes."""
    body = '<path id="a0" d="M0 0L1 1"/>'
    for level in range(1, levels + 1):
        body += f'<g id="a{level}">' + f'<use href="#a{level - 1}"/>' * 10 + "</g>"
    text = SVG.format(body)
    if size is not None:
        text = SVG.format("<!--" + " " * (size - len(text) - 7) + "-->" + body)
        assert len(text.encode()) == size
    return text


# -- SVG: what svgelements is never shown ----------------------------------------------------


def inherited(attribute: str) -> str:
    """A group whose every path inherits `attribute`, one of them the plain wing."""
    return SVG.format(f"<g {attribute}>{PLAIN}" + '<path d="M0 0L1 1"/>' * 50 + "</g>")


@pytest.mark.parametrize(
    "text",
    [
        SVG.format("<style>" + "a" * 40_000 + "</style>" + PLAIN),
        SVG.format("<style>" + "a" * 300_000 + "</style>" + PLAIN),
        SVG.format(PLAIN + '<text font="' + "normal " * 2000 + ';x">a</text>'),
        inherited('fill="rgb(' + "1" * 4000 + '"'),
        inherited('style="stroke:hsl(' + "1" * 4000 + '"'),
    ],
    ids=["style-40k", "style-300k", "font", "color", "color-in-style"],
)
def test_what_is_no_geometry_is_not_parsed_and_the_curve_is_right(text: str) -> None:
    """Each took svgelements' regular expressions quadratic time or worse (minutes for the
    300,000-character <style>); the reader process would have been killed at its limit."""
    expected = read_curve_text("plain.svg", SVG.format(PLAIN))
    for curve in (read_curve_isolated("attack.svg", text, "wing"), read_curve_text("a.svg", text)):
        np.testing.assert_allclose(curve.points, expected.points, atol=1e-12)
        assert curve.closed


def test_a_polyline_s_long_run_of_digits_is_read_as_its_number() -> None:
    """svgelements' pattern for points takes cubic time on a run of digits it cannot pair:
    1,000 of them, a 1 KB file, took it 17 s. A last number without its pair is dropped, as
    svgelements drops it."""
    text = SVG.format('<polyline id="leg" points="0,0 1,1 2,0 3,5 ' + "1" * 2000 + '"/>')
    curve = read_curve_isolated("leg.svg", text, "leg", points=4)
    np.testing.assert_allclose(curve.points[[0, -1]], [[0, 0], [3, -5]], atol=1e-9)


def test_a_transform_is_a_list_of_functions_of_bounded_length() -> None:
    text = SVG.format('<g transform="' + "scale(" * 100 + '">' + PLAIN + "</g>")
    with pytest.raises(ValueError, match=r"the transform of a <g> is not a list of functions"):
        read_curve_text("t.svg", text)
    long = SVG.format('<g transform="' + "scale(1) " * 200 + '">' + PLAIN + "</g>")
    with pytest.raises(CurveFileTooLarge) as caught:
        read_curve_text("t.svg", long)
    assert caught.value.limit == "MAX_SVG_ATTRIBUTE_CHARS"
    assert str(caught.value) == (
        "t.svg: the transform of a <g> holds 1,800 characters, more than the 1,000 an "
        "attribute may (path data and points aside)"
    )


@pytest.mark.parametrize("levels, size, elements", [(5, 1033, 246_907), (6, 1200, 2_469_128)])
def test_a_use_bomb_is_refused_naming_the_element_limit(
    levels: int, size: int, elements: int
) -> None:
    """Ten <use> of the level below, `levels` deep: svgelements made every copy (1,033 bytes
    took 19 s and 1 GB; 1.2 KB exhausted the memory). Counted, not made."""
    text = use_bomb(levels, size)
    with pytest.raises(CurveFileTooLarge) as caught:
        read_curve_text("bomb.svg", text)
    assert caught.value.limit == "MAX_SVG_ELEMENTS" and caught.value.status == 413
    assert str(caught.value) == (
        f"bomb.svg: {elements:,} elements, counting <use> copies, more than the "
        f"{MAX_SVG_ELEMENTS:,} an SVG may hold"
    )
    with pytest.raises(CurveFileTooLarge, match="elements, counting <use> copies"):
        read_curve_isolated("bomb.svg", text)


def test_a_use_is_still_read_and_one_containing_itself_is_refused() -> None:
    """A <use> draws its copy where it says, by href or xlink:href; CSS display:none in a
    style attribute still hides a shape."""
    plain = read_curve_text("plain.svg", SVG.format(PLAIN))
    for href in ('href="#wing"', 'xmlns:xlink="http://www.w3.org/1999/xlink" xlink:href="#wing"'):
        text = SVG.format(
            f'<defs>{PLAIN}</defs><g style="display:none"><path d="M0 0L9 9"/></g>'
            f'<use {href} x="10" y="-5"/>'
        )
        curve = read_curve_text("used.svg", text)
        np.testing.assert_allclose(curve.points, plain.points + np.array([10, 5]), atol=1e-9)
    loop = SVG.format('<g id="a"><path d="M0 0L1 1"/><use href="#a"/></g>')
    with pytest.raises(ValueError, match=r"^loop.svg: a <use> of #'a' contains itself$"):
        read_curve_text("loop.svg", loop)


def test_svg_entities_are_refused_and_a_doctype_alone_is_read() -> None:
    laughs = (
        '<?xml version="1.0"?><!DOCTYPE svg [<!ENTITY a "aaaaaaaaaa">'
        '<!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>'
        + SVG.format('<path id="wing" d="M0 0L1 1"><title>&b;</title></path>')
    )
    with pytest.raises(
        ValueError, match=r"^laughs.svg: declares the XML entity 'a': none is read$"
    ):
        read_curve_text("laughs.svg", laughs)
    doctype = (
        '<!DOCTYPE svg PUBLIC "-//W3C//DTD SVG 1.1//EN" '
        '"http://www.w3.org/Graphics/SVG/1.1/DTD/svg11.dtd">' + SVG.format(PLAIN)
    )
    expected = read_curve_text("plain.svg", SVG.format(PLAIN)).points
    np.testing.assert_allclose(read_curve_text("d.svg", doctype).points, expected)


def test_an_svg_past_its_limits_is_refused_naming_each() -> None:
    cases = {
        "MAX_SVG_ELEMENTS": SVG.format("<g/>" * MAX_SVG_ELEMENTS),
        "MAX_SVG_DEPTH": SVG.format("<g>" * 100 + "</g>" * 100),
        "MAX_SVG_NUMBERS": SVG.format(
            '<path d="M0 0' + " 1 1" * 20_000 + '"/>' + '<use href="#p"/>' * 2
            + '<path id="p" d="M0 0' + " 1 1" * 20_000 + '"/>'
        ),
        "MAX_SVG_TRANSFORMS": SVG.format(
            '<g transform="translate(1,2) rotate(3) scale(2)">' * 20
            + '<path d="M0 0L1 1"/>' * 1000 + "</g>" * 20
        ),
        "MAX_CURVE_SEGMENTS": SVG.format(
            '<path d="M0 0' + " L1 1 L0 0" * (MAX_CURVE_SEGMENTS // 2) + ' L5 5"/>'
        ),
    }  # fmt: skip
    said = {
        "MAX_SVG_ELEMENTS": "s.svg: more than the 10,000 elements an SVG may hold",
        "MAX_SVG_DEPTH": "s.svg: elements nested 101 deep, more than the 100 an SVG's may be",
        "MAX_SVG_NUMBERS": "s.svg: 160,012 numbers in its shapes' path data and points, "
        "counting <use> copies, more than the 100,000 an SVG may hold",
        "MAX_SVG_TRANSFORMS": "s.svg: 60,630 transform functions applied (each element "
        "applies its ancestors' too), counting <use> copies, more than the 50,000 an SVG "
        "may apply",
        "MAX_CURVE_SEGMENTS": "s.svg: (path, the first shape) has 10,001 segments, more than "
        "the 10,000 a curve may have",
    }
    for limit, text in cases.items():
        with pytest.raises(CurveFileTooLarge) as caught:
            read_curve_text("s.svg", text)
        assert (caught.value.limit, str(caught.value)) == (limit, said[limit])


def test_coordinates_past_the_limit_are_named() -> None:
    """Lengths among them overflowed: "cannot convert float NaN to integer" it said."""
    text = SVG.format('<path d="M0 0L1e305 0L1e305 1"/>')
    with pytest.raises(ValueError) as caught:
        read_curve_text("far.svg", text)
    assert str(caught.value) == "far.svg: coordinates must lie within +-1e+12, got 1e+305"
    with pytest.raises(ValueError, match=r"^far.csv: coordinates must lie within \+-1e\+12"):
        read_curve_text("far.csv", "0,0\n1,1\n1e305,2\n")
    with pytest.raises(ValueError, match=r"^inf.csv: coordinates must be finite numbers$"):
        read_curve_text("inf.csv", "0,0\n1,1\n1e400,2\n")


# -- DXF: a budget of points, on the curve itself ---------------------------------------------


def test_alternating_half_circle_bulges_read_on_their_circle_in_bounded_points() -> None:
    """1,000 vertices between (0, 0) and (1, 0), bulges +1 and -1: the lower half of the
    circle about (0.5, 0), back and forth. Flattened to 1e-8 of the drawing's size, it made
    7.85 million points (13 s, 800 MB); now FLAT_POINTS and at most 3 per segment, each on
    its circle, and the curve read lies on their chords: 21 to a half circle."""
    text = dxf_text(
        lambda space: space.add_lwpolyline(
            [(i % 2, 0, 0, 0, 1 if i % 2 == 0 else -1) for i in range(1000)], format="xyseb"
        )
    )
    outline, closed, _ = read_dxf("half.dxf", text.encode(), None)
    assert not closed and len(outline) <= 3 * 999 + FLAT_POINTS + 1
    np.testing.assert_allclose(np.linalg.norm(outline - [0.5, 0], axis=1), 0.5, rtol=1e-12)
    assert outline[:, 1].max() < 1e-12
    points = read_curve_isolated("half.dxf", text).points
    radius = np.linalg.norm(points - [0.5, 0], axis=1)
    assert np.all(radius <= 0.5 + 1e-12) and np.all(radius >= 0.5 * math.cos(math.pi / 42))
    assert points[:, 1].max() < 1e-12


def test_splines_through_1000_fit_points_are_read_on_the_spline() -> None:
    """Fit points around a circle: the spline through them lies on it (to about 1e-10 of its
    radius). Fit points at random: flattened to 1e-8 of its size it took 16 to 40 s; its
    curve runs from the first fit point to the last."""
    turn = np.linspace(0, 1.9 * math.pi, 1000)
    fit = np.column_stack([10 + 50 * np.cos(turn), 20 + 50 * np.sin(turn)])
    text = dxf_text(lambda space: space.add_spline(fit.tolist()))
    curve = read_curve_isolated("fit.dxf", text, points=1000)
    assert not curve.closed
    np.testing.assert_allclose(np.linalg.norm(curve.points - [10, 20], axis=1), 50, rtol=1e-7)
    np.testing.assert_allclose(curve.points[[0, -1]], fit[[0, -1]], atol=1e-9)
    scattered = np.random.default_rng(1).uniform(0, 100, (1000, 2))
    text = dxf_text(lambda space: space.add_spline(scattered.tolist()))
    curve = read_curve_isolated("scattered.dxf", text)
    np.testing.assert_allclose(curve.points[[0, -1]], scattered[[0, -1]], atol=1e-9)


def test_a_dxf_past_its_limits_is_refused_naming_each() -> None:
    def lwpolyline(space: Any) -> None:
        space.add_lwpolyline([(i, i % 3) for i in range(MAX_CURVE_SEGMENTS + 1)])

    def fit_spline(space: Any) -> None:
        space.add_spline([(i, i % 3) for i in range(MAX_SPLINE_FIT_POINTS + 1)])

    def control_spline(space: Any) -> None:
        space.add_open_spline([(i, i % 3) for i in range(MAX_CURVE_SEGMENTS + 1)])

    def many(space: Any) -> None:
        space.add_polyline2d([(i, i % 3) for i in range(MAX_DXF_ENTITIES)])

    said = {
        lwpolyline: (
            "MAX_CURVE_SEGMENTS",
            "p.dxf: the LWPOLYLINE on layer '0' has 10,001 vertices, more than the 10,000 a "
            "curve may have",
        ),
        fit_spline: (
            "MAX_SPLINE_FIT_POINTS",
            "p.dxf: the SPLINE on layer '0' has 1,001 fit points, more than the 1,000 a spline "
            "given by fit points alone may have",
        ),
        control_spline: (
            "MAX_CURVE_SEGMENTS",
            "p.dxf: the SPLINE on layer '0' has 10,001 control points, more than the 10,000 "
            "a curve may have",
        ),
        many: ("MAX_DXF_ENTITIES", "p.dxf: "),
    }
    for build, (limit, message) in said.items():
        with pytest.raises(CurveFileTooLarge) as caught:
            read_curve_text("p.dxf", dxf_text(build))
        assert caught.value.limit == limit and str(caught.value).startswith(message)
        if build is many:
            assert str(caught.value).endswith(
                "entities (and other records), more than the 20,000 a DXF file may hold"
            )


# -- JSON --------------------------------------------------------------------------------------


def test_json_too_deep_or_past_float64_is_a_value_error(tmp_path: Path) -> None:
    """They raised RecursionError and OverflowError: a 500 from /api/curve."""
    for name, text, problem in (
        ("deep.json", "[" * 50_000 + "]" * 50_000, "depth limit exceeded"),
        ("huge.json", "[[0, 0], [1, 1], [1" + "0" * 400 + ", 2]]", "infinity"),
    ):
        with pytest.raises(ValueError, match=rf"^{name}: not valid JSON \(.*{problem}"):
            read_curve_text(name, text)
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ValueError, match=rf"^cannot read points from {path}: .*{problem}"):
            read_points(path)
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf[[0, 0], [1, 1], [2, 0]]")
    assert read_points(bom) == [[0, 0], [1, 1], [2, 0]]
    assert read_curve(bom, points=3).points.shape == (3, 2)


# -- the reader processes -----------------------------------------------------------------------


@pytest.fixture
def one_reader() -> Iterator[CurveReaders]:
    with CurveReaders(readers=1, seconds=0.1, wait_s=0.1) as readers:
        readers.warm()
        yield readers


def wait_dead(pid: int) -> None:
    """Until the process `pid` has ended (a zombie counts: it reads no more)."""
    for _ in range(500):
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return
        if state in ("Z", "X"):
            return
        time.sleep(0.01)
    raise AssertionError(f"process {pid} did not end")


def test_a_file_past_the_time_limit_is_refused_and_its_reader_replaced(
    one_reader: CurveReaders,
) -> None:
    (first,) = one_reader.pids()
    with pytest.raises(CurveFileTooCostly) as caught:
        one_reader.read("heavy.svg", HEAVY)
    assert (caught.value.limit, caught.value.status) == ("CURVE_READ_SECONDS", 422)
    assert str(caught.value) == (
        "heavy.svg: reading it took longer than 0.1 s, the most a curve file is given"
    )
    wait_dead(first)
    assert one_reader.read("tiny.csv", TINY).points.shape == (400, 2)
    assert one_reader.pids() != [first]


def test_a_file_past_the_memory_limit_is_refused_and_its_reader_replaced() -> None:
    """The limit is set 100 MiB above what a reader takes once started; a JSON file of a
    million points takes more to parse."""
    with CurveReaders(readers=1) as readers:
        readers.warm()
        (pid,) = readers.pids()
        status = Path(f"/proc/{pid}/status").read_text()
        started = int(status.split("VmSize:")[1].split()[0]) * 1024
        limits = Path(f"/proc/{pid}/limits").read_text()
        assert f"Max address space         {readers.memory_bytes}" in limits
    memory = started + 100 * 2**20
    points = "[" + ",".join(["[0.5,1.5]"] * 2_000_000) + "]"
    with CurveReaders(readers=1, memory_bytes=memory) as readers:
        with pytest.raises(CurveFileTooCostly) as caught:
            readers.read("big.json", points)
        assert caught.value.limit == "CURVE_READER_MEMORY_BYTES"
        assert str(caught.value) == (
            f"big.json: reading it took more than the {memory / 2**20:,.0f} MiB of memory a "
            "reader is given"
        )
        assert readers.read("tiny.csv", TINY).points.shape == (400, 2)


def test_a_reader_killed_reading_or_idle_is_replaced() -> None:
    with CurveReaders(readers=1, seconds=60) as readers:
        readers.warm()
        (idle,) = readers.pids()
        os.kill(idle, signal.SIGKILL)
        wait_dead(idle)
        assert readers.read("tiny.csv", TINY).points.shape == (400, 2)  # not this file's fault
        (reading,) = readers.pids()
        assert reading != idle
        caught: list[BaseException] = []

        def read_heavy() -> None:
            try:
                readers.read("heavy.svg", HEAVY)
            except BaseException as exc:
                caught.append(exc)

        thread = threading.Thread(target=read_heavy)
        thread.start()
        while not readers.reading():
            time.sleep(0.001)
        os.kill(reading, signal.SIGKILL)
        thread.join()
        assert isinstance(caught[0], CurveFileTooCostly)
        assert caught[0].limit == "CURVE_READER_MEMORY_BYTES"
        assert str(caught[0]) == (
            "heavy.svg: reading it stopped its reader (killed by SIGKILL), most likely past "
            "the 1,024 MiB of memory a reader is given"
        )
        assert readers.read("tiny.csv", TINY).points.shape == (400, 2)


def test_readers_bound_how_many_read_at_once_and_turn_the_rest_away() -> None:
    with CurveReaders(readers=2, seconds=60, wait_s=0.05) as readers:
        results: list[object] = []
        threads = [
            threading.Thread(target=lambda: results.append(readers.read("heavy.svg", HEAVY)))
            for _ in range(2)
        ]
        for thread in threads:
            thread.start()
        while readers.reading() < 2:
            time.sleep(0.001)
        with pytest.raises(CurveReadersBusy) as caught:
            readers.read("tiny.csv", TINY)
        assert caught.value.status == 503
        assert str(caught.value) == (
            "tiny.csv: no curve reader came free within 0.05 s (all 2 busy): try again"
        )
        for thread in threads:
            thread.join()
        assert len(results) == 2 and len(readers.pids()) == 2
        expected = read_curve_text("heavy.svg", HEAVY).points
        for curve in results:
            np.testing.assert_array_equal(curve.points, expected)
        pids = readers.pids()
    for pid in pids:
        wait_dead(pid)
    with pytest.raises(RuntimeError, match="closed"):
        readers.read("tiny.csv", TINY)


def test_the_reader_answers_as_read_curve_text_does(one_reader: CurveReaders) -> None:
    """The same curve, the same errors with the same messages and types."""
    same = one_reader.read("plain.svg", SVG.format(PLAIN), "wing", points=97)
    expected = read_curve_text("plain.svg", SVG.format(PLAIN), "wing", points=97)
    np.testing.assert_array_equal(same.points, expected.points)
    assert (same.closed, same.source) == (expected.closed, expected.source)
    for name, text, kind in (
        ("none.svg", SVG.format("<text>no shapes</text>"), ValueError),
        ("broken.json", "[[1, 2], [3,", ValueError),
        ("bomb.svg", use_bomb(5), CurveFileTooLarge),
    ):
        with pytest.raises(kind) as here:
            read_curve_text(name, text)
        with pytest.raises(kind) as there:
            one_reader.read(name, text)
        assert str(there.value) == str(here.value) and type(there.value) is type(here.value)


def test_readers_run_below_their_caller_and_its_retrievals() -> None:
    """Every thread of a reader process runs at CURVE_READER_NICENESS, below the thread that
    started it and below a server's retrieval threads (RETRIEVAL_NICENESS)."""
    with CurveReaders(readers=1) as readers:
        readers.warm()
        (pid,) = readers.pids()
        threads = [int(task.name) for task in Path(f"/proc/{pid}/task").iterdir()]
        nice = {os.getpriority(os.PRIO_PROCESS, thread) for thread in threads}
        assert readers.read("tiny.csv", TINY).points.shape == (400, 2)
    assert nice == {CURVE_READER_NICENESS}
    assert CURVE_READER_NICENESS > RETRIEVAL_NICENESS > os.getpriority(os.PRIO_PROCESS, 0)
