"""Limits on user input, and the checks that enforce them.

The Python API, the CLI and the HTTP API check what users give them here, so that each limit has one
value and one message wherever it is hit. A refused input raises `ValueError` (its subclass
`InvalidMechanismError` for mechanisms) with a message naming the problem; the HTTP API answers it
with a 4xx and `{"error": <the message>}`. docs/reference/contract.md, Limits, lists them. Limits of
one subsystem alone live with it: drawing files in `interop.curve_limits`, HTTP requests in
`serve.http.limits`, synthesis options in `engine.synthesis.options`, design constraints in
`engine.synthesis.constraints`; the compiled kernels' buffer checks are `engine.buffers`.

Pure numpy: no numba, no Ray.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.node_kinds import ACTUATED, FIXED

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

# -- transmission angles -----------------------------------------------------------------------

#: Least transmission angle, in degrees, every dyad keeps at every check step.
DEFAULT_MIN_TRANSMISSION_DEG = 3.0
#: The most any least transmission angle may be asked to be (refinement's margin, generation's
#: and retrieval's thresholds): near 90 degrees no mechanism of several dyads is left.
MAX_TRANSMISSION_DEG = 45.0


class InvalidMechanismError(ValueError):
    """The input is not a simulable one-degree-of-freedom dyadic mechanism."""


def shown(value: object) -> str:
    """`value` for a message: its repr, cut short (a request may send megabytes)."""
    if isinstance(value, int | np.integer) and abs(int(value)).bit_length() > 128:
        # Python refuses to write out integers of more than 4,300 digits; none is needed.
        return f"an integer of {abs(int(value)).bit_length()} bits"
    text = str(int(value)) if isinstance(value, np.integer) else _repr_head(value, 40)
    return text if len(text) <= 40 else text[:37] + "..."


def _repr_head(value: object, limit: int) -> str:
    """repr(value), or a prefix of it longer than `limit`: a list or tuple is written only
    as far as needed, so a sequence of a million items costs what its first few do."""
    if not isinstance(value, list | tuple) or len(value) == 1:
        return repr(value)
    text = "[" if isinstance(value, list) else "("
    for i, item in enumerate(value):
        text += (", " if i else "") + _repr_head(item, limit - len(text))
        if len(text) > limit:
            return text
    return text + ("]" if isinstance(value, list) else ")")


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
    must be `wanted`: for ragged or non-numeric entries (text too, which NumPy would read as
    numbers), integers beyond float64's range and nesting too deep to walk. The caller checks
    the shape and finiteness."""
    try:
        array = np.asarray(value)
        if array.dtype.kind == "O" and all(_is_real(entry) for entry in array.flat):
            array = array.astype(np.float64)  # integers beyond int64 are numbers all the same
        if array.dtype.kind not in "biuf":
            raise ValueError(name)
        return array.astype(np.float64)
    except (TypeError, ValueError, OverflowError, RecursionError):
        raise ValueError(f"{name} must be {wanted}") from None


def _is_real(value: object) -> bool:
    """Whether `value` is a real number, as `as_real` takes them (bools are not)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


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
    within +-MAX_COORDINATE spanning at least MIN_EXTENT, or ValueError naming the problem.
    A list's count is checked before any of its entries is looked at."""
    if isinstance(points, list | tuple):
        check_point_count(len(points), name)
    try:
        array = np.asarray(points)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of [x, y] number pairs") from None
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be a list of [x, y] number pairs")
    array = array.astype(np.float64)
    # The count first: an empty list has no pairs to have a shape.
    if array.ndim:
        check_point_count(len(array), name)
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


def check_point_count(count: int, name: str = "points") -> None:
    """Refuse `count` drawn points unless MIN_POINTS to MAX_POINTS (ValueError naming `name`)."""
    if not MIN_POINTS <= count <= MAX_POINTS:
        raise ValueError(f"{name} must hold {MIN_POINTS} to {MAX_POINTS} pairs, got {count}")


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


# -- transmission angles ---------------------------------------------------------------------------


def as_transmission_deg(value: object, name: str = "min_transmission_deg") -> float:
    """A least transmission angle in degrees, from 0 to MAX_TRANSMISSION_DEG, or ValueError
    naming the option `name`."""
    degrees = as_real(name, value, "a number of degrees")
    if not 0.0 <= degrees <= MAX_TRANSMISSION_DEG:
        raise ValueError(
            f"{name} must be from 0 to {MAX_TRANSMISSION_DEG:g} degrees, got {degrees:g}"
        )
    return degrees


# -- numbers in a range ---------------------------------------------------------------------


def positive_at_most(value: object, name: str, maximum: float, kind: str, unit: str) -> float:
    """`value` as a float in (0, maximum], or ValueError naming `name`: "must be `kind`" when
    it is no number, its range in `unit` when out of it."""
    number = as_real(name, value, kind)
    if not 0.0 < number <= maximum:
        raise ValueError(
            f"{name} must be more than 0 and at most {maximum:g}{unit}, got {number:g}"
        )
    return number


# -- flags ------------------------------------------------------------------------------------


def as_flag(value: object, name: str) -> bool:
    """`value` as a bool, or ValueError naming `name`: only true or false are flags."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be true or false, got {shown(value)}")
    return bool(value)
