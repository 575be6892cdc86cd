"""Limits on user input, and the checks that enforce them.

The Python API, the CLI and the HTTP API check what users give them here, so that each limit
has one value and one message wherever it is hit. A refused input raises `ValueError` (its
subclass `InvalidMechanismError` for mechanisms) with a message naming the problem; the HTTP
API answers it with a 4xx and `{"error": <the message>}`. docs/reference/contract.md, Limits,
lists them.

Pure numpy: no numba, no Ray. The compiled kernels' entry points check their buffers here
too (`check_buffer`, `check_indices`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

FIXED, SIMPLE, ACTUATED = 0, 1, 2

# -- mechanisms -------------------------------------------------------------------------------

#: Largest mechanism the engine takes, in joints: finding the solution path is quadratic in the
#: joints, and no hand-drawn linkage comes near this.
MAX_JOINTS = 1000
#: The crank: joint 0 and joint 1.
MIN_JOINTS = 2
DEFAULT_STEPS = 200
MIN_STEPS, MAX_STEPS = 1, 100_000
#: Joints of a mechanism of the dataset (docs/reference/contract.md, Mechanisms).
MIN_DATASET_JOINTS, MAX_DATASET_JOINTS = 8, 20
#: Coordinates and link lengths the solver handles without its squares overflowing and without
#: its circles collapsing to points.
MAX_COORDINATE = 1e12
MIN_LINK_LENGTH = 1e-9

# -- retrieval queries ------------------------------------------------------------------------

MIN_POINTS, MAX_POINTS = 3, 10_000
#: A query spanning less than this has no curve to match (and its frame would not invert).
MIN_EXTENT = 1e-9
DEFAULT_K, MIN_K, MAX_K = 3, 1, 100
#: Largest drawing a target curve is read from (SVG, DXF, CSV, JSON), in bytes: refused before
#: it is parsed, since a parser holds the whole document, several times its size, in memory.
MAX_CURVE_FILE_BYTES = 32 * 1024 * 1024
#: Longest file name or element id (SVG id, DXF layer) a curve file is named by over HTTP.
MAX_CURVE_NAME_CHARS = 1000

# -- drawing files (interop.curve_files) ------------------------------------------------------

#: The most segments (an SVG path's), vertices (a DXF polyline's) or control points (a DXF
#: spline's) the curve read from a drawing may have: each costs Python work to flatten.
MAX_CURVE_SEGMENTS = 10_000
#: The most fit points of a DXF spline given by them alone: ezdxf finds its control points by
#: solving a dense system of that many equations.
MAX_SPLINE_FIT_POINTS = 1_000
#: The most entities a DXF file may hold, counting every record ezdxf makes an object of (a
#: POLYLINE's every VERTEX, table entries, objects): about 60 us and 1 KB apiece.
MAX_DXF_ENTITIES = 20_000
#: The most elements an SVG may hold, each `<use>` counted with the copy it makes of what it
#: refers to: svgelements makes every copy, about 100 us apiece.
MAX_SVG_ELEMENTS = 10_000
#: The deepest an SVG's elements may nest, `<use>` copies included.
MAX_SVG_DEPTH = 100
#: The most numbers (and path commands) in the path data and points of an SVG's shapes,
#: `<use>` copies counted: svgelements makes an object of each segment, about 15 us apiece.
MAX_SVG_NUMBERS = 100_000
#: The most transform functions svgelements may apply to an SVG's elements: each element
#: applies its own and all its ancestors' (`<use>` copies counted), about 20 us apiece.
MAX_SVG_TRANSFORMS = 50_000
#: The longest attribute an SVG element may have, but for path data and points (what
#: svgelements parses of an element is read again by every element below it).
MAX_SVG_ATTRIBUTE_CHARS = 1000
#: Seconds a reader process is given for one file (`interop.curve_worker`) before it is killed.
CURVE_READ_SECONDS = 5.0
#: The address space a reader process may take, its libraries' (about 350 MiB) included.
CURVE_READER_MEMORY_BYTES = 1024 * 1024 * 1024
#: Reader processes that read files at once, and the seconds a file waits for one of them.
CURVE_READERS = 2
CURVE_READER_WAIT_S = 2.0

# -- refinement (engine.refine) ----------------------------------------------------------------

#: Largest mechanism refinement takes, in joints: it keeps d(trajectory)/d(positions), joints x
#: steps x 2 x 2 joints numbers (32 MB at 50 joints and 200 steps).
MAX_REFINE_JOINTS = 50
#: Most simulation steps refinement takes (its derivatives grow with the steps).
MAX_REFINE_STEPS = 1000
#: Crank steps of the final check of a refined mechanism: finer than any simulation it is given,
#: so a lock or a dead centre between the simulation's steps is caught.
REFINE_CHECK_STEPS = 2000
DEFAULT_REFINE_ITERATIONS, MAX_REFINE_ITERATIONS = 200, 10_000
#: Least transmission angle, in degrees, every dyad keeps at every check step.
DEFAULT_MARGIN_DEG = 3.0
#: The most any least transmission angle may be asked to be (refinement's margin, generation's
#: and retrieval's thresholds): near 90 degrees no mechanism of several dyads is left.
MAX_TRANSMISSION_DEG = 45.0

# -- synthesis (engine.synthesis) ----------------------------------------------------------

#: Seconds a synthesis takes by default (retrieval included), and the most it may be given:
#: a synthesis holds a core for its whole budget, so a request may not hold one for long.
DEFAULT_SYNTHESIS_SECONDS, MAX_SYNTHESIS_SECONDS = 3.0, 30.0
#: Most refinement iterations a synthesis of fixed work may be given (`iterations`, summed over
#: its candidates): about what MAX_SYNTHESIS_SECONDS allow on two cores (docs/benchmarks.md,
#: Synthesis), so that fixed work holds a replica about as long as a timed one.
MAX_SYNTHESIS_ITERATIONS = 10_000
#: Seeds are what numpy's generators take whole: non-negative, here within 64 bits.
MAX_SEED = 2**64 - 1

# -- fabrication drawings (engine.fabrication) -------------------------------------------------

#: The crank length of an exported drawing, in millimetres, by default and at most (100 m).
DEFAULT_CRANK_MM, MAX_CRANK_MM = 20.0, 1e5
#: The most an exported drawing may span, in millimetres (1 km): a crank much shorter than the
#: other links would otherwise blow a drawing up past what any CAD program lays out.
MAX_DRAWING_MM = 1e6

# -- one HTTP request -------------------------------------------------------------------------

#: Largest mechanism one request may carry, in joints. Smaller than MAX_JOINTS: a request holds
#: a replica's CPU while it runs, and the studio draws nothing larger.
MAX_REQUEST_JOINTS = 100
#: Largest simulation one request may ask for: joints x steps (the answer holds twice as many
#: numbers, about 4 MB of JSON at the limit).
MAX_REQUEST_JOINT_STEPS = 100_000
#: Largest request body, in bytes (MAX_POINTS points take about 0.5 MB).
MAX_BODY_BYTES = 2 * 1024 * 1024
#: A request body must keep coming: a pause of BODY_TIMEOUT_S seconds with nothing of it, or
#: a body that falls behind MIN_BODY_BYTES_PER_S (after t seconds it must have sent
#: (t - BODY_TIMEOUT_S) x MIN_BODY_BYTES_PER_S bytes), is cut off with 408. A slow client
#: then holds a connection for at most BODY_TIMEOUT_S + MAX_BODY_BYTES / MIN_BODY_BYTES_PER_S
#: (138 s), however it sends.
BODY_TIMEOUT_S = 10.0
MIN_BODY_BYTES_PER_S = 16 * 1024


def request_limits() -> dict[str, float | int]:
    """The limits an HTTP request meets, by name, as `GET /api/limits` gives them to clients
    (the studio reads its own from there)."""
    return {
        "min_points": MIN_POINTS,
        "max_points": MAX_POINTS,
        "min_k": MIN_K,
        "max_k": MAX_K,
        "default_k": DEFAULT_K,
        "min_joints": MIN_JOINTS,
        "max_joints": MAX_REQUEST_JOINTS,
        "min_steps": MIN_STEPS,
        "max_steps": MAX_STEPS,
        "default_steps": DEFAULT_STEPS,
        "max_joint_steps": MAX_REQUEST_JOINT_STEPS,
        "max_seconds": MAX_SYNTHESIS_SECONDS,
        "max_iterations": MAX_SYNTHESIS_ITERATIONS,
        "default_seconds": DEFAULT_SYNTHESIS_SECONDS,
        "max_transmission_deg": MAX_TRANSMISSION_DEG,
        "max_coordinate": MAX_COORDINATE,
        "max_body_bytes": MAX_BODY_BYTES,
        "body_timeout_s": BODY_TIMEOUT_S,
        "min_body_bytes_per_s": MIN_BODY_BYTES_PER_S,
    }


class InvalidMechanismError(ValueError):
    """The input is not a simulable one-degree-of-freedom dyadic mechanism."""


def shown(value: object) -> str:
    """`value` for a message: its repr, cut short (a request may send megabytes)."""
    if isinstance(value, int | np.integer) and abs(int(value)).bit_length() > 128:
        # Python refuses to write out integers of more than 4,300 digits; none is needed.
        return f"an integer of {abs(int(value)).bit_length()} bits"
    text = str(int(value)) if isinstance(value, np.integer) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def as_real(name: str, value: object, kind: str = "a number") -> float:
    """`value`, a real number (bools are not), as a float; else ValueError naming `name` and
    saying it must be `kind`. An integer beyond float64's range is refused too, where
    `float()` would raise OverflowError: every numeric field of every input goes through here
    (or `as_real_array`), so that no number can escape as anything but a ValueError."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name} must be {kind}, got {shown(value)}")
    try:
        return float(value)
    except OverflowError:
        raise ValueError(
            f"{name} must be {kind} within +-{np.finfo(np.float64).max:.3g}, got {shown(value)}"
        ) from None


def as_real_array(name: str, value: object, wanted: str) -> np.ndarray:
    """`value` (nested sequences of numbers) as a float64 array, or ValueError saying `name`
    must be `wanted`: for ragged or non-numeric entries, integers beyond float64's range and
    nesting too deep to walk. The caller checks the shape and finiteness."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError, RecursionError):
        raise ValueError(f"{name} must be {wanted}") from None


def as_int(
    name: str,
    value: object,
    low: int,
    high: int | None = None,
    error: type[ValueError] = ValueError,
) -> int:
    """`value` as an int from `low` to `high` (no upper bound if None); bools are refused."""
    wanted = f"from {low} to {high}" if high is not None else f">= {low}"
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise error(f"{name} must be an integer {wanted}, got {shown(value)}")
    if value < low or (high is not None and value > high):
        raise error(f"{name} must be {wanted}, got {shown(value)}")
    return int(value)


def as_steps(steps: object) -> int:
    """A step count from 1 to MAX_STEPS, or InvalidMechanismError."""
    return as_int("steps", steps, MIN_STEPS, MAX_STEPS, InvalidMechanismError)


# -- mechanism arrays -------------------------------------------------------------------------


def as_int_array(name: str, value: ArrayLike, ndim: int) -> np.ndarray:
    """`value` as an int64 array of `ndim` dimensions; bools count, fractions and NaN do not."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise InvalidMechanismError(f"{name} is not a rectangular array: {exc}") from None
    if array.ndim != ndim:
        raise InvalidMechanismError(f"{name} must be {ndim}-D, got shape {array.shape}")
    if array.dtype == bool:
        return array.astype(np.int64)
    if not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)):
        raise InvalidMechanismError(f"{name} must be numeric, got dtype {array.dtype}")
    if np.issubdtype(array.dtype, np.floating):
        if not np.all(np.isfinite(array)):
            raise InvalidMechanismError(f"{name} has NaN or infinite entries")
        if np.any(array != np.round(array)):
            raise InvalidMechanismError(f"{name} must hold whole numbers")
    return array.astype(np.int64)


def as_graph(adjacency: ArrayLike, node_types: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(adjacency, node_types) as int64 arrays if they form a mechanism graph: a symmetric 0/1
    matrix with zero diagonal of 2 to MAX_JOINTS joints, and one known type per joint.

    Raises `InvalidMechanismError` naming the first problem found.
    """
    adj = as_int_array("adjacency", adjacency, 2)
    types = as_int_array("node_types", node_types, 1)
    n = adj.shape[0]
    if adj.shape != (n, n):
        raise InvalidMechanismError(f"adjacency must be square, got shape {adj.shape}")
    if n < MIN_JOINTS:
        raise InvalidMechanismError(
            f"a mechanism needs at least {MIN_JOINTS} joints (the crank), got {n}"
        )
    if n > MAX_JOINTS:
        raise InvalidMechanismError(f"at most {MAX_JOINTS} joints are supported, got {n}")
    if types.shape != (n,):
        raise InvalidMechanismError(
            f"node_types must have one entry per joint ({n}), got {types.shape[0]}"
        )
    bad = np.argwhere((adj != 0) & (adj != 1))
    if len(bad):
        i, j = bad[0]
        raise InvalidMechanismError(
            f"adjacency entries must be 0 or 1, got {adj[i, j]} at ({i}, {j})"
        )
    if np.any(np.diag(adj)):
        i = int(np.flatnonzero(np.diag(adj))[0])
        raise InvalidMechanismError(f"self-link: adjacency[{i}, {i}] must be 0")
    asym = np.argwhere(adj != adj.T)
    if len(asym):
        i, j = asym[0]
        raise InvalidMechanismError(
            f"adjacency is not symmetric: [{i}, {j}] = {adj[i, j]} but [{j}, {i}] = {adj[j, i]}"
        )
    bad_types = np.flatnonzero((types < FIXED) | (types > ACTUATED))
    if len(bad_types):
        i = int(bad_types[0])
        raise InvalidMechanismError(
            f"node_types must be 0 (fixed), 1 (simple) or 2 (actuated); joint {i} is {types[i]}"
        )
    return adj, types


def as_positions(positions: ArrayLike, n_joints: int, *, batch: bool = False) -> np.ndarray:
    """`positions` as a C-contiguous float64 array of shape (n, 2), or (B, n, 2) with `batch`."""
    shape = "(B, n, 2)" if batch else "(n, 2)"
    try:
        array = np.asarray(positions)
    except (TypeError, ValueError) as exc:
        raise InvalidMechanismError(f"positions is not a rectangular array: {exc}") from None
    if array.dtype == bool or not (
        np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)
    ):
        raise InvalidMechanismError(f"positions must be numeric, got dtype {array.dtype}")
    expected_ndim = 3 if batch else 2
    if array.ndim != expected_ndim or array.shape[-2:] != (n_joints, 2):
        raise InvalidMechanismError(
            f"positions must have shape {shape} with n = {n_joints}, got {array.shape}"
        )
    array = np.ascontiguousarray(array, dtype=np.float64)
    if not np.all(np.isfinite(array)):
        raise InvalidMechanismError("positions has NaN or infinite entries")
    return array


def link_pairs(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(i, j) of every link of `adjacency`, i < j, in row order."""
    i, j = np.nonzero(np.triu(adjacency, 1))
    return i, j


def check_positions(
    adjacency: np.ndarray,
    positions: np.ndarray,
    links: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Refuse degenerate geometry (batch-aware): coordinates beyond MAX_COORDINATE, and linked
    joints closer than MIN_LINK_LENGTH, the crank included. `links` is `link_pairs(adjacency)`
    if the caller keeps it."""
    if positions.size and np.abs(positions).max() > MAX_COORDINATE:
        raise InvalidMechanismError(f"positions must lie within +-{MAX_COORDINATE:g}")
    i, j = link_pairs(adjacency) if links is None else links
    gaps = positions[..., i, :] - positions[..., j, :]
    # Squared lengths first, a wide margin below which the lengths themselves are measured:
    # most calls then take no square root.
    squares = np.einsum("...k,...k->...", gaps, gaps)
    if squares.size and squares.min() < (2 * MIN_LINK_LENGTH) ** 2:
        short = np.linalg.norm(gaps, axis=-1) < MIN_LINK_LENGTH
        if np.any(short):
            k = int(np.flatnonzero(short.reshape(-1, len(i)).any(axis=0))[0])
            what = (
                "the crank has zero length" if (i[k], j[k]) == (0, 1) else "a link has zero length"
            )
            raise InvalidMechanismError(
                f"{what}: joints {i[k]} and {j[k]} are closer than {MIN_LINK_LENGTH:g}"
            )


# -- retrieval queries ------------------------------------------------------------------------


def as_drawn_points(points: object, name: str = "points") -> np.ndarray:
    """Drawn points as a float64 (T, 2) array: MIN_POINTS to MAX_POINTS finite [x, y] pairs
    within +-MAX_COORDINATE spanning at least MIN_EXTENT, or ValueError naming the problem."""
    try:
        array = np.asarray(points)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of [x, y] number pairs") from None
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be a list of [x, y] number pairs")
    array = array.astype(np.float64)
    # The count first: an empty list has no pairs to have a shape.
    if array.ndim and not MIN_POINTS <= len(array) <= MAX_POINTS:
        raise ValueError(f"{name} must hold {MIN_POINTS} to {MAX_POINTS} pairs, got {len(array)}")
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"{name} must be [x, y] pairs, got an array of shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite numbers")
    if np.any(np.abs(array) > MAX_COORDINATE):
        raise ValueError(f"{name} must lie within +-{MAX_COORDINATE:g}")
    if np.all(array == array[0]):
        raise ValueError(f"{name} are all the same point: there is no curve")
    if np.ptp(array, axis=0).max() < MIN_EXTENT:
        raise ValueError(f"{name} span less than {MIN_EXTENT:g}: there is no curve to match")
    return array


def validate_query(points: object, k: object = DEFAULT_K) -> tuple[np.ndarray, int]:
    """A retrieval query as a float64 (T, 2) array and k, or ValueError naming the problem."""
    k = as_int("k", k, MIN_K, MAX_K)
    return as_drawn_points(points), k


def as_max_joints(value: object, name: str = "max_joints") -> int | None:
    """The most joints an answer's reduced mechanism may have: None (any), or an integer from
    MIN_JOINTS (the crank alone, whose joint 1 traces a circle; 3 and 4 joints trace circles
    and arcs too, a four-bar's coupler point needs 5) to MAX_DATASET_JOINTS; ValueError naming
    `name` otherwise."""
    if value is None:
        return None
    return as_int(name, value, MIN_JOINTS, MAX_DATASET_JOINTS)


# -- refinement -------------------------------------------------------------------------------


def as_transmission_deg(value: object, name: str = "margin_deg") -> float:
    """A least transmission angle in degrees, from 0 to MAX_TRANSMISSION_DEG, or ValueError
    naming the option `name`."""
    degrees = as_real(name, value, "a number of degrees")
    if not 0.0 <= degrees <= MAX_TRANSMISSION_DEG:
        raise ValueError(
            f"{name} must be from 0 to {MAX_TRANSMISSION_DEG:g} degrees, got {degrees:g}"
        )
    return degrees


def check_refine_size(n_joints: int, steps: int) -> None:
    """Refuse a refinement whose derivatives would be too large (MAX_REFINE_JOINTS joints,
    MAX_REFINE_STEPS steps)."""
    if n_joints > MAX_REFINE_JOINTS:
        raise InvalidMechanismError(
            f"refinement takes at most {MAX_REFINE_JOINTS} joints, got {n_joints}"
        )
    if steps > MAX_REFINE_STEPS:
        raise ValueError(f"refinement takes at most {MAX_REFINE_STEPS} steps, got {steps}")


# -- fabrication drawings ---------------------------------------------------------------------


def _positive_at_most(value: object, name: str, maximum: float, kind: str, unit: str) -> float:
    """`value` as a float in (0, maximum], or ValueError naming `name`: "must be `kind`" when
    it is no number, its range in `unit` when out of it."""
    number = as_real(name, value, kind)
    if not 0.0 < number <= maximum:
        raise ValueError(
            f"{name} must be more than 0 and at most {maximum:g}{unit}, got {number:g}"
        )
    return number


def as_crank_mm(value: object, name: str = "crank_mm") -> float:
    """A crank length in millimetres: more than 0 and at most MAX_CRANK_MM, or ValueError
    naming the option `name`."""
    return _positive_at_most(value, name, MAX_CRANK_MM, "a number of millimetres", " mm")


# -- synthesis --------------------------------------------------------------------------------


def as_seconds(value: object) -> float:
    """A synthesis time budget in seconds: more than 0 and at most MAX_SYNTHESIS_SECONDS;
    None gives DEFAULT_SYNTHESIS_SECONDS."""
    if value is None:
        return DEFAULT_SYNTHESIS_SECONDS
    return _positive_at_most(value, "seconds", MAX_SYNTHESIS_SECONDS, "a number", "")


def as_flag(value: object, name: str) -> bool:
    """`value` as a bool, or ValueError naming `name`: only true or false are flags."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be true or false, got {shown(value)}")
    return bool(value)


def validate_synthesis_work(
    seconds: object = None, seed: object = None, iterations: object = None
) -> tuple[float | None, int, int | None]:
    """How much work a synthesis does, as (seconds, seed, iterations): a time budget (seconds,
    None for the default) or a fixed amount of work (iterations, 1 to MAX_SYNTHESIS_ITERATIONS,
    with seconds None), and the seed of its random restarts (0 to MAX_SEED; None gives 0).
    Raises ValueError naming the problem."""
    seed = 0 if seed is None else as_int("seed", seed, 0, MAX_SEED)
    if iterations is None:
        return (None if seconds is None else as_seconds(seconds)), seed, None
    iterations = as_int("iterations", iterations, 1, MAX_SYNTHESIS_ITERATIONS)
    if seconds is not None:
        raise ValueError(
            "give seconds or iterations, not both: iterations fix the work whatever the time"
        )
    return None, seed, iterations


#: The design constraints a synthesis takes (`as_constraints`), in the drawing's units.
CONSTRAINT_NAMES = ("pivots", "footprint", "max_link_ratio", "min_link", "max_link")


@dataclass(frozen=True)
class Constraints:
    """What a designer fixes, in the drawing's own units and frame (None: not constrained).

    `pivots` (xmin, ymin, xmax, ymax): every fixed joint inside this box. `footprint`: every
    joint inside this box through the whole crank turn. `max_link_ratio`: the longest link at
    most this many times the shortest. `min_link`, `max_link`: every link's length within.
    """

    pivots: tuple[float, float, float, float] | None = None
    footprint: tuple[float, float, float, float] | None = None
    max_link_ratio: float | None = None
    min_link: float | None = None
    max_link: float | None = None

    def given(self) -> tuple[str, ...]:
        """The names of the constraints set."""
        return tuple(name for name in CONSTRAINT_NAMES if getattr(self, name) is not None)


def _as_box(value: object, name: str) -> tuple[float, float, float, float]:
    """[xmin, ymin, xmax, ymax] as four finite floats, each min below its max."""
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__"):
        raise ValueError(f"{name} must be a box [xmin, ymin, xmax, ymax], got {shown(value)}")
    box = as_real_array(name, value, "four numbers [xmin, ymin, xmax, ymax]")
    if box.shape != (4,) or any(isinstance(v, bool) for v in value):  # type: ignore[union-attr]
        raise ValueError(f"{name} must be four numbers [xmin, ymin, xmax, ymax]")
    if not np.all(np.isfinite(box)) or np.any(np.abs(box) > MAX_COORDINATE):
        raise ValueError(f"{name} must be finite numbers within +-{MAX_COORDINATE:g}")
    if not (box[0] < box[2] and box[1] < box[3]):
        raise ValueError(f"{name} must have xmin < xmax and ymin < ymax, got {box.tolist()}")
    xmin, ymin, xmax, ymax = (float(v) for v in box)
    return xmin, ymin, xmax, ymax


def as_constraints(value: object) -> Constraints | None:
    """Design constraints from a mapping of CONSTRAINT_NAMES (or a `Constraints`); None or an
    empty mapping gives None. Raises ValueError naming an unknown or bad constraint."""
    if value is None or isinstance(value, Constraints):
        return value if value is None or value.given() else None
    if not isinstance(value, dict):
        raise ValueError(f"constraints must be an object of {', '.join(CONSTRAINT_NAMES)}")
    for name in value:
        if name not in CONSTRAINT_NAMES:
            raise ValueError(
                f"unknown constraint {shown(name)}: constraints are {', '.join(CONSTRAINT_NAMES)}"
            )
    given = {name: v for name, v in value.items() if v is not None}
    boxes = {name: _as_box(given[name], name) for name in ("pivots", "footprint") if name in given}
    lengths = {
        name: _positive_at_most(given[name], name, MAX_COORDINATE, "a length", "")
        for name in ("min_link", "max_link")
        if name in given
    }
    ratio = None
    if "max_link_ratio" in given:
        ratio = _positive_at_most(given["max_link_ratio"], "max_link_ratio", 1e6, "a number", "")
        if ratio < 1.0:
            raise ValueError(f"max_link_ratio must be at least 1, got {ratio:g}")
    low, high = lengths.get("min_link"), lengths.get("max_link")
    if low is not None and high is not None and low > high:
        raise ValueError(f"min_link ({low:g}) must not exceed max_link ({high:g})")
    if not given:
        return None
    return Constraints(max_link_ratio=ratio, **boxes, **lengths)


def as_timing(timing: object, count: int, partial: bool) -> np.ndarray | None:
    """Crank angles in radians (count,) at which the drawn points are to be reached, relative
    to the first: `True` is equal steps of a whole turn, a list gives them in degrees; None or
    False is no timing. Raises ValueError naming the problem."""
    if timing is None or timing is False:
        return None
    if timing is True:
        if partial:
            raise ValueError(
                "timing=true spreads the points over a whole turn, which a partial stroke "
                "does not make: give the stroke's crank angles as a list"
            )
        return 2.0 * np.pi * np.arange(count) / count
    if isinstance(timing, str | bytes | dict) or not hasattr(timing, "__len__"):
        raise ValueError(f"timing must be true or a list of angles in degrees, got {shown(timing)}")
    if any(isinstance(v, bool) for v in timing):  # type: ignore[union-attr]
        raise ValueError("timing must be true or a list of angles in degrees")
    degrees = as_real_array("timing", timing, "true or a list of angles in degrees")
    if degrees.ndim != 1 or len(degrees) != count:
        raise ValueError(f"timing must give one angle per point: {count}, got {degrees.size}")
    if not np.all(np.isfinite(degrees)) or np.any(np.abs(degrees) > 1e6):
        raise ValueError("timing must be finite angles in degrees within +-1e6")
    return np.radians(degrees - degrees[0])


def validate_synthesis(
    points: object, k: object = DEFAULT_K, seconds: object = None, partial: object = False
) -> tuple[np.ndarray, int, float, bool]:
    """A synthesis request as (points (T, 2) float64, k, seconds, partial), or ValueError
    naming the problem."""
    points, k = validate_query(points, k)
    return points, k, as_seconds(seconds), as_flag(partial, "partial")


# -- compiled kernels' buffers ----------------------------------------------------------------


def _shape_text(shape: tuple[int | None, ...]) -> str:
    parts = ["any" if side is None else str(side) for side in shape]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def _an(text: str) -> str:
    return (
        "an " if text.startswith(("int", "integer", "unsigned", "a", "e", "o")) else "a "
    ) + text


def check_buffer(
    name: str,
    array: object,
    shape: tuple[int | None, ...],
    dtype: type | str = np.float64,
    *,
    contiguous: bool = False,
    writeable: bool = False,
) -> None:
    """Refuse a buffer a compiled kernel would index past its end, or misread: unless `array`
    is a NumPy array of `shape` (None: any length on that axis) and `dtype` (a type, or kind
    characters such as "iu" for any integer), C-contiguous where `contiguous` and writeable
    where `writeable`, ValueError naming it, what was expected and what was given. numba
    checks no bounds: without this a short buffer is written past its end, silently.

    Costs about a microsecond; kernels called in loops by their own module, with buffers made
    there, are called without it."""
    if type(array) is np.ndarray:
        kind_ok = array.dtype.kind in dtype if isinstance(dtype, str) else array.dtype == dtype
        given = array.shape
        if (
            kind_ok
            and (not contiguous or array.flags.c_contiguous)
            and (not writeable or array.flags.writeable)
            and (
                given == shape
                or (
                    len(given) == len(shape)
                    and all(w is None or w == g for g, w in zip(given, shape, strict=True))
                )
            )
        ):
            return
    wanted_type = {"iu": "integer", "u": "unsigned integer", "f": "float"}.get(
        dtype, str(np.dtype(dtype)) if not isinstance(dtype, str) else f"kind {dtype!r}"
    )
    wanted = _an(
        f"{'writeable ' if writeable else ''}{'C-contiguous ' if contiguous else ''}"
        f"{wanted_type} array of shape {_shape_text(shape)}"
    )
    if not isinstance(array, np.ndarray):
        got = _an(type(array).__name__)
    else:
        layout = "" if array.flags.c_contiguous or not contiguous else "non-contiguous "
        frozen = "" if array.flags.writeable or not writeable else "read-only "
        got = _an(f"{frozen}{layout}{array.dtype} array of shape {_shape_text(array.shape)}")
    raise ValueError(f"{name} must be {wanted}, got {got}")


def check_indices(name: str, values: np.ndarray, limit: int, of: str) -> None:
    """Refuse indices a compiled kernel would follow out of bounds: unless every one of
    `values` lies in [0, limit), ValueError naming them and `of`, what they index."""
    if values.size and not (values.min() >= 0 and values.max() < limit):
        bad = values[(values < 0) | (values >= limit)].flat[0]
        raise ValueError(f"{name} must index {of} (0 to {limit - 1}), got {shown(bad)}")


def check_solution_path(
    order: object, joints: int, fixed: object = None, positions: str = "pos"
) -> None:
    """Refuse a solution path `order` (m, 3) of (joint, parent_a, parent_b) rows, or fixed
    joints `fixed` (f,), naming a joint outside the `joints` of the positions given with them
    (the buffer called `positions`), and positions without the crank's two joints."""
    if joints < MIN_JOINTS:
        raise ValueError(f"{positions} must hold at least the crank's 2 joints, got {joints}")
    of = f"the {joints} joints of {positions}"
    check_buffer("order", order, (None, 3), "iu")
    check_indices("order", order, joints, of)  # type: ignore[arg-type]
    if fixed is not None:
        check_buffer("fixed", fixed, (None,), "iu")
        check_indices("fixed", fixed, joints, of)  # type: ignore[arg-type]


def check_packed_paths(
    orders: np.ndarray,
    order_start: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
) -> None:
    """Refuse packed mechanisms (`search.mechanisms.MechanismBank`: solution paths `orders`
    (R, 3), `order_start` and `joint_start` (M + 1,)) and the (mechanisms[i], joints[i]) a
    kernel is to follow in them, naming the first bad buffer: a mechanism outside the M held,
    a joint outside its mechanism, or offsets that decrease."""
    check_buffer("orders", orders, (None, 3), "iu")
    check_buffer("order_start", order_start, (None,), "iu")
    count = order_start.shape[0] - 1
    check_buffer("joint_start", joint_start, (count + 1,), "iu")
    check_buffer("mechanisms", mechanisms, (None,), "iu")
    rows = mechanisms.shape[0]
    check_buffer("joints", joints, (rows,), "iu")
    if count < 0:
        raise ValueError("order_start must hold at least one entry, got none")
    check_indices("order_start", order_start, orders.shape[0] + 1, "the rows of orders")
    check_indices("mechanisms", mechanisms, count, f"the {count} mechanisms held")
    if rows:
        sizes = joint_start[mechanisms + 1] - joint_start[mechanisms]
        if (sizes < MIN_JOINTS).any() or (
            order_start[mechanisms + 1] < order_start[mechanisms]
        ).any():
            raise ValueError("order_start and joint_start must not decrease")
        if not ((joints >= 0) & (joints < sizes)).all():
            i = int(np.flatnonzero((joints < 0) | (joints >= sizes))[0])
            raise ValueError(
                f"joints must index each mechanism's joints: joints[{i}] = {int(joints[i])}, "
                f"mechanism {int(mechanisms[i])} has {int(sizes[i])}"
            )
