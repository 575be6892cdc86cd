"""Curves that real mechanisms trace, for `links bench synthesize --set`: a mechanism exists
that draws each one exactly, so the best score there is 0.

A curve is drawn from its own seed: a random topology of 6 to 12 joints (the dataset's rules),
one valid set of initial positions found by the engine's sequential sampler, simulated over a
crank turn. The curve is the path of the joint solved last (the one that hangs on the most
links) among those that draw neither an arc nor a circle, nor go back over themselves: none of
those is the kind of curve a designer brings. A mechanism with no such joint is drawn again.
The path is traced at TRACED_STEPS steps. The seeds are apart from any dataset's
(`TRACED_SALT`), and a random position is never drawn twice, so no curve is a dataset path.

The bench measures these curves by `synthesis.dense_score` as well: the sampled chamfer of a
result keeps a floor of a few thousandths even for the mechanism that drew the curve.

Pure numpy and the engine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.mechanism import analyze_topology, arc_flags
from links_ray.engine.kinematics.paths import is_circle, normalize_path
from links_ray.engine.kinematics.sampling import PositionSampler, PositionSearchError
from links_ray.engine.kinematics.solver import TopologySimulator, simulate
from links_ray.engine.kinematics.topology import random_topology
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS

#: Curves drawn, and the default seed of their generator.
TRACED_CURVES = 12
TRACED_SEED = 0
#: Joints of the mechanisms drawn, both ends included.
TRACED_JOINTS = (6, 12)
#: A path whose points mostly lie this near (of its longest chord) to another part of it
#: goes back over itself (`retraces`).
RETRACE_GAP = 0.01
#: Mechanisms drawn for one curve before the generator gives up (a few suffice).
MAX_DRAWS = 1000
#: Steps the curve is traced at.
TRACED_STEPS = REFINE_CHECK_STEPS
#: Mixed into every curve's seed, so no dataset seed draws the same mechanisms.
TRACED_SALT = 0x7472_6163_6564


@dataclass(frozen=True)
class TracedCurve:
    """A curve and the mechanism that traces it."""

    points: np.ndarray  # (TRACED_STEPS, 2): the joint's path over a crank turn
    adjacency: np.ndarray  # (n, n) uint8
    node_types: np.ndarray  # (n,) int8
    positions: np.ndarray  # (n, 2) initial positions
    joint: int  # the moving joint that traces the curve


def traced_curves(seed: int = TRACED_SEED, count: int = TRACED_CURVES) -> dict[str, TracedCurve]:
    """`count` traced curves, named `traced_00`, `traced_01`, ..., drawn from `seed`; curve i
    depends on (seed, i) alone."""
    return {f"traced_{i:02d}": traced_curve(seed, i) for i in range(count)}


def traced_curve(seed: int, index: int) -> TracedCurve:
    """Curve `index` of the traced curves of `seed` (see the module's docstring)."""
    rng = np.random.default_rng([TRACED_SALT, seed, index])
    for _ in range(MAX_DRAWS):
        n_joints = int(rng.integers(TRACED_JOINTS[0], TRACED_JOINTS[1] + 1))
        adjacency, node_types = random_topology(rng, n_joints)
        simulator = TopologySimulator(adjacency, node_types)
        try:
            found = PositionSampler(simulator, steps=DEFAULT_STEPS).search(1, rng)
        except PositionSearchError:
            continue
        trajectories = found.trajectories[0]
        is_arc = arc_flags(adjacency[None], node_types[None])[0]
        for joint in analyze_topology(adjacency, node_types).order[::-1, 0]:
            path = trajectories[joint]
            normalized = normalize_path(path)
            if not (is_arc[joint] or is_circle(normalized) or retraces(normalized)):
                positions = found.positions[0]
                # Dense, so that the curve's polyline is the mechanism's curve to within a
                # hair: a mechanism that traces it scores near 0 however the set spaces it.
                dense = simulate(adjacency, node_types, positions, TRACED_STEPS)[joint]
                return TracedCurve(dense, adjacency, node_types, positions, int(joint))
    raise ValueError(f"no traced curve {index} of seed {seed} kept in {MAX_DRAWS} draws")


def retraces(normalized: np.ndarray) -> bool:
    """Whether a normalized closed path goes back over itself: half its points lie within
    RETRACE_GAP of a point that is more than a tenth of the turn away. A joint carried rigidly
    by a rocker swings to and fro on an arc, though no fixed joint is its neighbour."""
    n = len(normalized)
    gaps = np.linalg.norm(normalized[:, None, :] - normalized[None, :, :], axis=-1)
    along = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    gaps[np.minimum(along, n - along) <= n // 10] = np.inf
    return bool(np.median(gaps.min(axis=1)) < RETRACE_GAP)
