"""An independent simulator that picks each joint's assembly by the nearest point.

Peer simulators solve a dyad at each crank step by intersecting its two circles and keeping
the intersection nearest the joint's position at the step before. links-ray freezes each
dyad's branch (the side of its parents' line) at the start instead. The two agree while no
dyad comes near a dead centre, where its two intersections meet. This one is plain numpy and
shares no code with the engine: it finds its own solving order from the graph.

Run as a script for the figures of docs/benchmarks.md:
`python tests/support/nearest_point.py [PER_FLOOR]`.
"""

from __future__ import annotations

import sys

import numpy as np

#: Largest joint coordinate difference, over all joints and steps, of "the same simulation".
SAME = 1e-6


def solving_order(adjacency: np.ndarray, node_types: np.ndarray) -> list[tuple[int, int, int]]:
    """(joint, parent, parent) rows: each simple joint after two joints already known."""
    known = set(np.flatnonzero(node_types != 1).tolist())  # fixed joints and the crank tip
    order = []
    while len(known) < len(node_types):
        for joint in range(len(node_types)):
            parents = [k for k in np.flatnonzero(adjacency[joint]) if k in known]
            if joint not in known and len(parents) >= 2:
                order.append((joint, int(parents[0]), int(parents[1])))
                known.add(joint)
                break
        else:
            raise ValueError("not dyadic")
    return order


def nearest_point_simulate(
    adjacency: np.ndarray, node_types: np.ndarray, positions: np.ndarray, steps: int = 200
) -> np.ndarray | None:
    """(n, steps, 2) trajectories, or None when some dyad cannot be assembled at some step.

    The crank tip turns about joint 0 from its initial angle by 2 pi / steps a step, as the
    dataset's crank does.
    """
    positions = np.asarray(positions, dtype=np.float64)
    n = len(node_types)
    order = solving_order(adjacency, node_types)
    radius = {
        (j, p): np.linalg.norm(positions[j] - positions[p]) for j, a, b in order for p in (a, b)
    }
    centre, tip = positions[0], positions[1]
    crank_radius = np.linalg.norm(tip - centre)
    start = np.arctan2(*(tip - centre)[::-1])
    out = np.empty((n, steps, 2))
    previous = positions.copy()
    for t in range(steps):
        pose = previous.copy()
        angle = start + 2 * np.pi * t / steps
        pose[1] = centre + crank_radius * np.array([np.cos(angle), np.sin(angle)])
        for j, a, b in order:
            ra, rb = radius[(j, a)], radius[(j, b)]
            gap = pose[b] - pose[a]
            d = np.linalg.norm(gap)
            if d == 0 or d > ra + rb or d < abs(ra - rb):
                return None
            along = (d * d + ra * ra - rb * rb) / (2 * d)
            height = np.sqrt(max(ra * ra - along * along, 0.0))
            foot = pose[a] + along * gap / d
            normal = np.array([-gap[1], gap[0]]) / d
            candidates = (foot + height * normal, foot - height * normal)
            pose[j] = min(candidates, key=lambda p: np.linalg.norm(p - previous[j]))
        out[:, t] = pose
        previous = pose
    return out


def agreement(per_floor: int, seed: int = 0) -> dict[str, tuple[int, int]]:
    """(agreeing, of) valid random mechanisms of 8-20 joints: the first `per_floor` drawn, and
    the first `per_floor` keeping at least 10 and at least 20 degrees of least transmission
    angle (drawn on until each floor has them, as `links generate --min-transmission` does)."""
    import links_ray
    from links_ray.engine.kinematics.mechanism import analyze_topology
    from links_ray.engine.kinematics.transmission import mechanism_transmission_deg

    rng = np.random.default_rng(seed)
    floors = {"all": 0.0, "10": 10.0, "20": 20.0}
    tally = {key: [0, 0] for key in floors}
    while any(of < per_floor for _, of in tally.values()):
        adjacency, node_types = links_ray.random_topology(rng)
        positions = links_ray.sample_positions(adjacency, node_types, 1, seed=rng)[0]
        ours = links_ray.simulate(adjacency, node_types, positions)
        order = analyze_topology(adjacency, node_types).order
        angle = mechanism_transmission_deg(order, ours[None].astype(np.float32))[0]
        wanted = [
            key for key, floor in floors.items() if angle >= floor and tally[key][1] < per_floor
        ]
        if not wanted:
            continue
        theirs = nearest_point_simulate(adjacency, node_types, positions)
        same = theirs is not None and np.abs(theirs - ours).max() < SAME
        for key in wanted:
            tally[key][0] += same
            tally[key][1] += 1
    return {key: (agree, of) for key, (agree, of) in tally.items()}


if __name__ == "__main__":
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 500
    for key, (agree, of) in agreement(count).items():
        print(f"{key}: {agree} of {of} agree ({agree / max(of, 1):.1%})")
