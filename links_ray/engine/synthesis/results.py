"""A synthesis's answer: each candidate as a result (`as_result`), the list of them with what
the constraints left unmet (`SynthesisResults`), and `fit`, the measure a result reports.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.kinematics.transmission import joint_transmission_deg
from links_ray.engine.synthesis.candidates import Candidate
from links_ray.engine.synthesis.refinement.checks import target_error
from links_ray.engine.synthesis.target import Target, as_target, target_chamfer

__all__ = ["SynthesisResults", "as_result", "fit"]


class SynthesisResults(list):
    """A synthesis's results (a list of result dicts, best first, or a Pareto front by
    joints), and `unmet`: when constraints were given and no candidate keeps them,
    {"constraint", "by"} of the candidate that came nearest (the most missed constraint, and
    by how much in its units), else None. `iterations`: the refinement iterations done (each
    attempt counts one at least); `stopped`: whether the work was called off before its end."""

    unmet: dict[str, Any] | None = None
    iterations: int = 0
    stopped: bool = False


def fit(
    points: object,
    positions: object,
    adjacency: object,
    node_types: object,
    joint: int,
    partial: bool = False,
) -> tuple[float, tuple[int, int] | None]:
    """(chamfer divided by the drawing's longest chord, interval) of the path `joint` traces
    at DEFAULT_STEPS steps against the drawn `points`; `interval` is (start step, count) of the
    run matched to a partial stroke, else None."""
    target = as_target(points, partial)
    path = simulate(adjacency, node_types, positions, DEFAULT_STEPS)[joint]
    value, interval = target_chamfer(target, path)
    return value / target.chord, interval


def as_result(
    candidate: Candidate,
    target: Target,
    timed: Target | None = None,
    trajectories: bool = False,
    elapsed: float | None = None,
    stopped: bool | None = None,
) -> dict[str, Any]:
    """A candidate as an answer (docs/reference/contract.md, HTTP API, describes it), with its
    `timed_error` against a `timed` target; a progress report adds every joint's
    `trajectories` and the `elapsed_ms` since the synthesis began. The answer's results (given
    whether the work was `stopped`) say whether refinement kept a step of it (`refined`) and,
    if not, `why` (`Candidate.why_unrefined`)."""
    topology = candidate.topology
    positions = candidate.positions
    path = simulate(topology.adjacency, topology.node_types, positions, DEFAULT_STEPS)
    value, interval = target_chamfer(target, path[candidate.joint])
    result = candidate.result
    answer: dict[str, Any] = {
        "path_id": result["path_id"],
        "mechanism_id": result["mechanism_id"],
        "chamfer": value / target.chord,
        "retrieved_chamfer": candidate.retrieved,
        "mechanism": {
            "adjacency": topology.adjacency.tolist(),
            "node_types": topology.node_types.tolist(),
            "positions": positions.tolist(),
        },
        "mechanism_joint": candidate.joint,
        # Coupler points added to the retrieved mechanism (`engine.synthesis.coupler_points`): 0
        # when it is the retrieved one, moved.
        "coupler_points": candidate.coupler_points,
        "n_joints": topology.n_joints,
        "n_links": int(np.count_nonzero(np.triu(topology.adjacency, 1))),
        # As the dataset's paths state it: the joint's dyads, at the stored steps.
        "min_transmission_deg": float(
            joint_transmission_deg(topology.order, path[None])[0, candidate.joint]
        ),
        "path": path[candidate.joint].tolist(),
        "interval": None,
    }
    if timed is not None:
        error, _ = target_error(timed, topology, positions, candidate.joint, path[candidate.joint])
        answer["timed_error"] = error / timed.chord
    if interval is not None:
        start, count = interval
        answer["interval"] = {
            "start_step": start,
            "steps": count,
            "start_deg": 360.0 * start / DEFAULT_STEPS,
            "sweep_deg": 360.0 * (count - 1) / DEFAULT_STEPS,
        }
    if stopped is not None:
        why = candidate.why_unrefined(stopped)
        answer["refined"], answer["why"] = why is None, why
    if trajectories:
        answer["trajectories"] = path.tolist()
    if elapsed is not None:
        answer["elapsed_ms"] = round(elapsed * 1e3, 3)
    return answer
