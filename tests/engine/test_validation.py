"""Input validation (docs/reference/contract.md, Mechanisms, Python API): bad mechanisms refused.

Every case must raise `InvalidMechanismError` (a `ValueError`) naming the problem, through each
public entry point: `simulate`, `simulate_batch` and `TopologySimulator` (construction for
topology problems, `.simulate` / `.first_lock` for position and step problems).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import pytest

from links_ray import (
    InvalidMechanismError,
    LockingError,
    TopologySimulator,
    simulate,
    simulate_batch,
)
from links_ray.engine import inputs
from links_ray.engine.fabrication import limits as fabrication_limits
from links_ray.engine.synthesis import constraints
from links_ray.engine.synthesis import options as synthesis_options

# A valid crank-rocker with a coupler point: O2, A (crank tip), B, O4, C on the coupler.
LINKS = [(0, 1), (1, 2), (2, 3), (1, 4), (2, 4)]
NODE_TYPES = [0, 2, 1, 0, 1]
POSITIONS = [[0.5, 0.5], [0.55, 0.5], [0.6, 0.8], [0.8, 0.5], [0.7, 0.7]]


def adjacency_of(n: int, links: Sequence[tuple[int, int]]) -> list[list[int]]:
    """Symmetric 0/1 adjacency, as plain nested lists, of `n` joints with the given links."""
    adjacency = [[0] * n for _ in range(n)]
    for i, j in links:
        adjacency[i][j] = adjacency[j][i] = 1
    return adjacency


ADJACENCY = adjacency_of(5, LINKS)


def spread_positions(n: int) -> list[list[float]]:
    """`n` distinct, generic positions (no linked pair coincides)."""
    rng = np.random.default_rng(n)
    return rng.uniform(0.0, 1.0, (n, 2)).tolist()


def batched(positions: object) -> object:
    """A batch of one: the positions wrapped in a list (keeps malformed input malformed)."""
    return [positions]


def assert_refused(
    match: str,
    adjacency: object,
    node_types: object,
    positions: object,
    steps: object = 200,
) -> None:
    """Every entry point raises InvalidMechanismError (a ValueError) matching `match`."""
    calls: list[tuple[str, Callable[[], object]]] = [
        ("simulate", lambda: simulate(adjacency, node_types, positions, steps)),
        (
            "simulate_batch",
            lambda: simulate_batch(adjacency, node_types, batched(positions), steps),
        ),
        (
            "TopologySimulator.simulate",
            lambda: TopologySimulator(adjacency, node_types).simulate(batched(positions), steps),
        ),
        (
            "TopologySimulator.first_lock",
            lambda: TopologySimulator(adjacency, node_types).first_lock(batched(positions), steps),
        ),
    ]
    for name, call in calls:
        with pytest.raises(InvalidMechanismError, match=match) as info:
            call()
        assert isinstance(info.value, ValueError), name
        assert not isinstance(info.value, LockingError), name


def assert_topology_refused(
    match: str, adjacency: object, node_types: object, positions: object | None = None
) -> None:
    """A topology problem: refused by the constructor too, and by every entry point."""
    with pytest.raises(InvalidMechanismError, match=match):
        TopologySimulator(adjacency, node_types)
    if positions is None:
        positions = spread_positions(len(node_types))  # type: ignore[arg-type]
    assert_refused(match, adjacency, node_types, positions)


def test_error_classes() -> None:
    """InvalidMechanismError and LockingError are ValueErrors, and distinct."""
    assert issubclass(InvalidMechanismError, ValueError)
    assert issubclass(LockingError, ValueError)
    assert not issubclass(InvalidMechanismError, LockingError)
    assert not issubclass(LockingError, InvalidMechanismError)


def test_reference_mechanism_is_valid() -> None:
    """The mechanism the malformed cases are derived from simulates fine."""
    trajectories = simulate(ADJACENCY, NODE_TYPES, POSITIONS)
    assert trajectories.shape == (5, 200, 2) and np.isfinite(trajectories).all()


# --------------------------------------------------------------------------------------------
# Shapes and types
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("adjacency", "match"),
    [
        pytest.param([0, 1, 1, 0], r"adjacency must be 2-D, got shape \(4,\)", id="1-D"),
        pytest.param(
            np.zeros((5, 5, 1)), r"adjacency must be 2-D, got shape \(5, 5, 1\)", id="3-D"
        ),
        pytest.param(
            np.zeros((5, 4)), r"adjacency must be square, got shape \(5, 4\)", id="non-square"
        ),
        pytest.param(None, r"adjacency must be 2-D, got shape \(\)", id="None"),
        pytest.param(
            [["0", "1"], ["1", "0"]], r"adjacency must be numeric, got dtype <U1", id="strings"
        ),
        pytest.param("adjacency", r"adjacency must be 2-D, got shape \(\)", id="a string"),
        pytest.param([[0, 1, 0], [1, 0]], r"adjacency is not a rectangular array", id="ragged"),
        pytest.param(
            [[0, None], [None, 0]],
            r"adjacency must be numeric, got dtype object",
            id="None entries",
        ),
        pytest.param(
            np.ones((2, 2), dtype=complex),
            r"adjacency must be numeric, got dtype complex",
            id="complex",
        ),
    ],
)
def test_malformed_adjacency(adjacency: object, match: str) -> None:
    """Adjacency that is not a square numeric matrix."""
    assert_topology_refused(match, adjacency, NODE_TYPES, POSITIONS)


def test_single_joint_refused() -> None:
    """A mechanism needs at least the two crank joints."""
    assert_topology_refused(r"at least 2 joints", [[0]], [0], [[0.5, 0.5]])
    assert_topology_refused(r"at least 2 joints", np.zeros((0, 0)), [], np.zeros((0, 2)))


@pytest.mark.parametrize(
    ("node_types", "match"),
    [
        pytest.param(
            [0, 2, 1, 0], r"node_types must have one entry per joint \(5\), got 4", id="too short"
        ),
        pytest.param([0, 2, 1, 0, 1, 1], r"one entry per joint \(5\), got 6", id="too long"),
        pytest.param([[0, 2, 1, 0, 1]], r"node_types must be 1-D, got shape \(1, 5\)", id="2-D"),
        pytest.param(None, r"node_types must be 1-D, got shape \(\)", id="None"),
        pytest.param(["0", "2", "1", "0", "1"], r"node_types must be numeric", id="strings"),
        pytest.param([0, 2, [1, 0], 0, 1], r"node_types is not a rectangular array", id="ragged"),
        pytest.param([0, 2, 1.5, 0, 1], r"node_types must hold whole numbers", id="fractional"),
        pytest.param([0, 2, np.nan, 0, 1], r"node_types has NaN or infinite entries", id="NaN"),
        pytest.param([0, 2, np.inf, 0, 1], r"node_types has NaN or infinite entries", id="inf"),
        pytest.param([0, 2, 3, 0, 1], r"node_types must be 0 .*joint 2", id="type 3"),
        pytest.param([0, 2, -1, 0, 1], r"node_types must be 0 .*joint 2", id="type -1"),
    ],
)
def test_malformed_node_types(node_types: object, match: str) -> None:
    """node_types that is not one known joint type per joint."""
    assert_topology_refused(match, ADJACENCY, node_types, POSITIONS)


@pytest.mark.parametrize(
    ("positions", "match"),
    [
        pytest.param(
            POSITIONS[:4],
            r"positions must have shape \((B, )?n, 2\) with n = 5, got \((1, )?4, 2\)",
            id="too few joints",
        ),
        pytest.param(
            [[*p, 0.0] for p in POSITIONS], r"with n = 5, got \((1, )?5, 3\)", id="(n, 3)"
        ),
        pytest.param(np.ravel(POSITIONS).tolist(), r"with n = 5, got \((1, )?10,?\)", id="flat"),
        pytest.param(None, r"positions must be numeric, got dtype object", id="None"),
        pytest.param(
            [[str(x) for x in p] for p in POSITIONS],
            r"positions must be numeric, got dtype <U",
            id="strings",
        ),
        pytest.param([*POSITIONS[:4], [0.7]], r"positions is not a rectangular array", id="ragged"),
        pytest.param(
            [*POSITIONS[:4], [0.7, None]],
            r"positions must be numeric, got dtype object",
            id="None entry",
        ),
        pytest.param(
            np.ones((5, 2), dtype=bool), r"positions must be numeric, got dtype bool", id="bool"
        ),
        pytest.param(
            [*POSITIONS[:4], [0.7, np.nan]], r"positions has NaN or infinite entries", id="NaN"
        ),
        pytest.param(
            [*POSITIONS[:4], [np.inf, 0.7]], r"positions has NaN or infinite entries", id="inf"
        ),
        pytest.param(
            [*POSITIONS[:4], [0.7, -np.inf]], r"positions has NaN or infinite entries", id="-inf"
        ),
    ],
)
def test_malformed_positions(positions: object, match: str) -> None:
    """positions that is not a finite (n, 2) float array."""
    assert_refused(match, ADJACENCY, NODE_TYPES, positions)


def test_batch_positions_need_a_batch_axis() -> None:
    """simulate_batch and TopologySimulator want (B, n, 2), not a single (n, 2) pose."""
    with pytest.raises(InvalidMechanismError, match=r"\(B, n, 2\)"):
        simulate_batch(ADJACENCY, NODE_TYPES, POSITIONS)
    with pytest.raises(InvalidMechanismError, match=r"\(B, n, 2\)"):
        TopologySimulator(ADJACENCY, NODE_TYPES).simulate(POSITIONS)
    with pytest.raises(InvalidMechanismError, match=r"\(B, n, 2\)"):
        TopologySimulator(ADJACENCY, NODE_TYPES).first_lock(np.zeros((2, 4, 2)))


def test_one_bad_row_refuses_the_batch() -> None:
    """A NaN in any row of a batch is malformed input, not a locking candidate."""
    batch = np.array([POSITIONS, POSITIONS, POSITIONS])
    batch[2, 3, 1] = np.nan
    with pytest.raises(InvalidMechanismError, match=r"NaN"):
        simulate_batch(ADJACENCY, NODE_TYPES, batch)


# --------------------------------------------------------------------------------------------
# Adjacency contents
# --------------------------------------------------------------------------------------------


def with_entries(*entries: tuple[int, int, float]) -> np.ndarray:
    """The reference adjacency (float) with some entries overwritten."""
    adjacency = np.array(ADJACENCY, dtype=float)
    for i, j, value in entries:
        adjacency[i, j] = value
    return adjacency


@pytest.mark.parametrize(
    ("adjacency", "match"),
    [
        pytest.param(
            with_entries((0, 3, np.nan), (3, 0, np.nan)),
            r"adjacency has NaN or infinite entries",
            id="NaN",
        ),
        pytest.param(
            with_entries((0, 3, np.inf), (3, 0, np.inf)),
            r"adjacency has NaN or infinite entries",
            id="inf",
        ),
        pytest.param(
            with_entries((1, 2, 2), (2, 1, 2)), r"must be 0 or 1, got 2 at \(1, 2\)", id="2"
        ),
        pytest.param(with_entries((1, 2, -1), (2, 1, -1)), r"0 or 1, got -1 at \(1, 2\)", id="-1"),
        pytest.param(
            with_entries((1, 2, 0.5), (2, 1, 0.5)), r"adjacency must hold whole numbers", id="0.5"
        ),
        pytest.param(
            with_entries((0, 2, 1)),
            r"not symmetric: \[0, 2\] = 1 but \[2, 0\] = 0",
            id="asymmetric",
        ),
        pytest.param(
            with_entries((2, 1, 0)),
            r"not symmetric: \[1, 2\] = 1 but \[2, 1\] = 0",
            id="one-sided link",
        ),
        pytest.param(
            with_entries((2, 2, 1)), r"self-link: adjacency\[2, 2\] must be 0", id="self-link"
        ),
        pytest.param(
            with_entries((0, 0, 1)), r"self-link: adjacency\[0, 0\] must be 0", id="self-link at 0"
        ),
    ],
)
def test_malformed_adjacency_entries(adjacency: np.ndarray, match: str) -> None:
    """Adjacency entries that are not a symmetric 0/1 matrix with zero diagonal."""
    assert_topology_refused(match, adjacency, NODE_TYPES, POSITIONS)


# --------------------------------------------------------------------------------------------
# Crank and joint types
# --------------------------------------------------------------------------------------------


def test_no_crank() -> None:
    """Joints 0 and 1 must be linked (the crank)."""
    links = [(0, 2), (1, 2), (2, 3), (1, 4), (2, 4)]
    assert_topology_refused(r"no crank", adjacency_of(5, links), NODE_TYPES, POSITIONS)


@pytest.mark.parametrize(
    ("node_types", "match"),
    [
        pytest.param([1, 2, 1, 0, 1], r"joint 0 must be fixed", id="joint 0 simple"),
        pytest.param([2, 1, 1, 0, 1], r"joint 0 must be fixed", id="joint 0 actuated"),
        pytest.param([0, 1, 1, 0, 1], r"joint 1 must be the actuated", id="joint 1 simple"),
        pytest.param([0, 0, 1, 0, 1], r"joint 1 must be the actuated", id="joint 1 fixed"),
        pytest.param([0, 2, 2, 0, 1], r"only joint 1 may be actuated", id="two actuated"),
        pytest.param([0, 2, 1, 0, 2], r"only joint 1 may be actuated", id="last actuated"),
    ],
)
def test_wrong_crank_joints(node_types: list[int], match: str) -> None:
    """Joint 0 fixed, joint 1 the one actuated joint."""
    assert_topology_refused(match, ADJACENCY, node_types, POSITIONS)


def test_link_between_fixed_joints() -> None:
    """Ground links are not links: two fixed joints may not be linked."""
    adjacency = adjacency_of(5, [*LINKS, (0, 3)])
    assert_topology_refused(r"two fixed joints", adjacency, NODE_TYPES, POSITIONS)


# --------------------------------------------------------------------------------------------
# Mobility and solvability
# --------------------------------------------------------------------------------------------


def test_simple_joint_on_three_fixed_joints() -> None:
    """A simple joint linked to three fixed joints is over-constrained."""
    adjacency = adjacency_of(5, [(0, 1), (2, 0), (2, 3), (2, 4)])
    assert_topology_refused(r"over-constrained", adjacency, [0, 2, 1, 0, 0])


def test_simple_joint_on_three_known_joints() -> None:
    """Crank tip plus two fixed joints: three known neighbours is one too many."""
    adjacency = adjacency_of(5, [(0, 1), (1, 2), (2, 3), (2, 4)])
    assert_topology_refused(r"over-constrained", adjacency, [0, 2, 1, 0, 0])


def test_crank_joint_linked_to_another_fixed_joint() -> None:
    """The crank joint 1 also linked to a fixed joint cannot turn."""
    adjacency = adjacency_of(5, [*LINKS, (1, 3)])
    assert_topology_refused(r"over-constrained", adjacency, NODE_TYPES, POSITIONS)


def test_redundant_link_between_independent_dyads() -> None:
    """Joints 2 and 4 are each solved from the crank and a fixed pivot; linking them is
    redundant (2 * moving - links = 0)."""
    links = [(0, 1), (1, 2), (2, 3), (1, 4), (4, 5), (2, 4)]
    assert_topology_refused(r"over-constrained", adjacency_of(6, links), [0, 2, 1, 0, 1, 0])


def test_redundant_link_downstream() -> None:
    """A link between two joints of separate dyad chains, further from the crank."""
    links = [(0, 1), (1, 2), (2, 3), (1, 4), (4, 5), (2, 6), (4, 6), (6, 7), (2, 7), (3, 7)]
    # Joint 7 has three known neighbours (6, 2 and fixed 3).
    assert_topology_refused(r"over-constrained", adjacency_of(8, links), [0, 2, 1, 0, 1, 0, 1, 1])


def test_triad_is_not_dyadic() -> None:
    """A one-DOF loop (an Assur triad: ternary link 2-3-4 hung from joint 1 and two fixed
    pivots) where no joint ever has two known neighbours."""
    links = [(0, 1), (2, 3), (3, 4), (2, 4), (1, 2), (3, 5), (4, 6)]
    node_types = [0, 2, 1, 1, 1, 0, 0]
    moving, n_links = 4, len(links)
    assert 2 * moving - n_links == 1
    assert_topology_refused(r"dyadic", adjacency_of(7, links), node_types)


def test_double_butterfly_like_loop_is_not_dyadic() -> None:
    """A dyadic four-bar followed by a triad driven from its coupler: 1 DOF, not dyadic."""
    # Four-bar 0-1-2-3 solves joint 2; the triad 4-5-6 (ternary link) hangs from 2, 7 and 8.
    links = [(0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (4, 6), (2, 4), (5, 7), (6, 8)]
    node_types = [0, 2, 1, 0, 1, 1, 1, 0, 0]
    moving = sum(t != 0 for t in node_types)
    assert 2 * moving - len(links) == 1
    assert_topology_refused(r"not dyadic-solvable", adjacency_of(9, links), node_types)


def test_dangling_joint_is_more_than_one_dof() -> None:
    """A simple joint with a single link is not determined by the crank."""
    adjacency = adjacency_of(6, [*LINKS, (4, 5)])
    assert_topology_refused(r"more than one degree of freedom", adjacency, [*NODE_TYPES, 1])


def test_five_bar_is_more_than_one_dof() -> None:
    """A five-bar (two moving joints between the crank and a fixed pivot) has two DOF."""
    adjacency = adjacency_of(5, [(0, 1), (1, 2), (2, 3), (3, 4)])
    assert_topology_refused(r"more than one degree of freedom", adjacency, [0, 2, 1, 1, 0])


def test_unlinked_simple_joint_is_more_than_one_dof() -> None:
    """A simple joint with no links at all."""
    adjacency = adjacency_of(6, LINKS)
    assert_topology_refused(r"more than one degree of freedom", adjacency, [*NODE_TYPES, 1])


# --------------------------------------------------------------------------------------------
# Degenerate geometry and steps
# --------------------------------------------------------------------------------------------


def test_zero_length_crank() -> None:
    """Joint 1 on top of joint 0: the crank has zero length."""
    positions = [POSITIONS[0], POSITIONS[0], *POSITIONS[2:]]
    match = r"the crank has zero length: joints 0 and 1 are closer than 1e-09"
    assert_refused(match, ADJACENCY, NODE_TYPES, positions)


def test_zero_length_link() -> None:
    """Two linked joints at one point."""
    positions = [*POSITIONS[:4], POSITIONS[2]]
    match = r"a link has zero length: joints 2 and 4 are closer than 1e-09"
    assert_refused(match, ADJACENCY, NODE_TYPES, positions)


def test_coincident_dyad_parents_lock_at_step_0() -> None:
    """Joint 2's two parents (crank tip 1 and fixed pivot 3) start at the same point, so its two
    circles share a centre: well-formed input (1 and 3 are not linked) that cannot be
    assembled, a lock at step 0 of joint 2 through every entry point."""
    positions = [POSITIONS[0], POSITIONS[1], POSITIONS[2], POSITIONS[1], POSITIONS[4]]
    with pytest.raises(LockingError, match=r"^mechanism locks at step 0: joint 2 ") as info:
        simulate(ADJACENCY, NODE_TYPES, positions)
    assert (info.value.step, info.value.node) == (0, 2)
    trajectories, valid = simulate_batch(ADJACENCY, NODE_TYPES, [positions])
    assert valid.tolist() == [False] and np.isnan(trajectories).all()
    lock_step, lock_node = TopologySimulator(ADJACENCY, NODE_TYPES).first_lock([positions])
    assert (lock_step.tolist(), lock_node.tolist()) == ([0], [2])


@pytest.mark.parametrize(
    "steps",
    [0, -1, 2.5, 200.5, "200", True, False, None, np.bool_(True), 100_001],
    ids=repr,
)
def test_invalid_steps(steps: object) -> None:
    """steps must be an integer from 1 to 100,000 (not a bool, float or string)."""
    match = r"^steps must be (an integer )?from 1 to 100000, got "
    assert_refused(match, ADJACENCY, NODE_TYPES, POSITIONS, steps)


@pytest.mark.parametrize("steps", [1, 2, np.int64(50), np.int32(7), 360])
def test_valid_steps(steps: object) -> None:
    """Python and numpy integers are accepted."""
    assert simulate(ADJACENCY, NODE_TYPES, POSITIONS, steps).shape == (5, int(steps), 2)


# --------------------------------------------------------------------------------------------
# Accepted input forms
# --------------------------------------------------------------------------------------------


def test_accepted_input_forms() -> None:
    """Plain lists, bool adjacency, float node types with whole values and int positions
    give the same trajectories as canonical numpy input."""
    expected = simulate(
        np.array(ADJACENCY, dtype=np.uint8),
        np.array(NODE_TYPES, dtype=np.int8),
        np.array(POSITIONS, dtype=np.float64),
    )
    variants = [
        (ADJACENCY, NODE_TYPES, POSITIONS),
        (np.array(ADJACENCY, dtype=bool), NODE_TYPES, POSITIONS),
        ([[bool(x) for x in row] for row in ADJACENCY], NODE_TYPES, POSITIONS),
        (np.array(ADJACENCY, dtype=float), [float(t) for t in NODE_TYPES], POSITIONS),
        (ADJACENCY, np.array(NODE_TYPES, dtype=np.float32), np.array(POSITIONS, np.float32)),
        (np.array(ADJACENCY, dtype=np.int64), tuple(NODE_TYPES), tuple(map(tuple, POSITIONS))),
        (ADJACENCY, NODE_TYPES, np.asfortranarray(POSITIONS)),
    ]
    for adjacency, node_types, positions in variants:
        got = simulate(adjacency, node_types, positions)
        if np.asarray(positions).dtype == np.float32:
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
        else:
            np.testing.assert_array_equal(got, expected)
        trajectories, valid = simulate_batch(adjacency, node_types, [positions])
        assert valid.tolist() == [True]
        np.testing.assert_array_equal(trajectories[0], got)


def test_integer_positions_accepted() -> None:
    """Whole-number positions (an int array) are fine: scaled four-bar on an integer grid."""
    positions = [[0, 0], [1, 0], [2, 6], [6, 0], [4, 4]]
    expected = simulate(ADJACENCY, NODE_TYPES, np.array(positions, dtype=float))
    np.testing.assert_array_equal(simulate(ADJACENCY, NODE_TYPES, positions), expected)


def test_isolated_fixed_joint_accepted() -> None:
    """An unlinked fixed joint constrains nothing and is simply carried along."""
    adjacency = adjacency_of(6, LINKS)
    positions = [*POSITIONS, [0.1, 0.9]]
    got = simulate(adjacency, [*NODE_TYPES, 0], positions)
    np.testing.assert_array_equal(got[5], np.broadcast_to([0.1, 0.9], (200, 2)))
    np.testing.assert_array_equal(got[:5], simulate(ADJACENCY, NODE_TYPES, POSITIONS))


def test_empty_batch() -> None:
    """A batch of no position sets gives empty results, not an error."""
    trajectories, valid = simulate_batch(ADJACENCY, NODE_TYPES, np.zeros((0, 5, 2)))
    assert trajectories.shape == (0, 5, 200, 2) and valid.shape == (0,)


def test_inputs_not_modified() -> None:
    """The caller's arrays are left untouched."""
    adjacency = np.array(ADJACENCY)
    node_types = np.array(NODE_TYPES)
    positions = np.array([POSITIONS, POSITIONS])
    copies = adjacency.copy(), node_types.copy(), positions.copy()
    simulate_batch(adjacency, node_types, positions)
    simulate(adjacency, node_types, positions[0])
    for before, after in zip(copies, (adjacency, node_types, positions), strict=True):
        np.testing.assert_array_equal(before, after)


# -- numbers past float64 ----------------------------------------------------------------------

#: An integer no float64 holds, as json.loads reads a long run of digits.
HUGE = 10**400


@pytest.mark.parametrize(
    ("check", "match"),
    [
        (lambda v: synthesis_options.as_seconds(v), "seconds must be a number within"),
        (lambda v: inputs.as_transmission_deg(v, "min_transmission"), "min_transmission must be"),
        (
            lambda v: fabrication_limits.as_crank_mm(v),
            "crank_mm must be a number of millimetres within",
        ),
        (lambda v: constraints.as_constraints({"min_link": v}), "min_link must be a length within"),
        (lambda v: constraints.as_constraints({"max_link_ratio": v}), "max_link_ratio must be"),
        (lambda v: constraints.as_constraints({"pivots": [0, 0, v, 1]}), "pivots must be four"),
        (lambda v: constraints.as_constraints({"footprint": [-v, 0, 1, 1]}), "footprint must be"),
        (
            lambda v: synthesis_options.as_timing([0, v, 2], 3, False),
            "timing must be true or a list",
        ),
        (
            lambda v: synthesis_options.as_timing([0, [[v]], 2], 3, False),
            "timing must be true or a list",
        ),
        (lambda v: inputs.validate_query([[0, 0], [1, 1], [v, 2]]), "points must be a list"),
        (lambda v: inputs.validate_query([[0, 0], [1, 1]], v), "k must be from 1 to 100"),
        (lambda v: synthesis_options.SynthesisOptions(seed=v), "seed must be from 0 to"),
        (lambda v: synthesis_options.SynthesisOptions(iterations=v), "iterations must be from 1"),
        (lambda v: inputs.as_max_joints(v), "max_joints must be from 2 to 20"),
    ],
)
@pytest.mark.parametrize("value", [HUGE, -HUGE, 10**5000], ids=["10^400", "-10^400", "10^5000"])
def test_every_numeric_field_refuses_numbers_past_float64(
    check: Callable[[object], object], match: str, value: int
) -> None:
    """Every validator answers an integer beyond float64 with a ValueError naming its field,
    never OverflowError (which a server would answer 500); and the message never writes the
    number out (Python refuses to, past 4,300 digits)."""
    with pytest.raises(ValueError, match=match) as refused:
        check(value)
    assert len(str(refused.value)) < 300


def test_a_refused_value_is_shown_as_its_repr_cut_short_however_long() -> None:
    """Error messages show a value as its repr cut to 40 characters; a list or tuple is
    written only as far as that needs (a request's list of a million numbers included), and
    the text is the same as the whole repr's, cut."""
    from links_ray.engine.inputs import shown

    def cut(value: object) -> str:
        text = repr(value)
        return text if len(text) <= 40 else text[:37] + "..."

    values: list[object] = [
        [0.0] * 1_000_000,
        [[0.5] * 1_000_000],
        [[1, 2], [3, 4]],
        (1,),
        (1, 2),
        [],
        (),
        [[]],
        [(1,), (2, 3)],
        [1, [2, [3, [4, [5]]]]],
        ["x" * 100],
        list(range(12)),
        {"a": [1] * 100},
    ]
    for value in values:
        assert shown(value) == cut(value)
