"""Target curves for `links bench synthesize`: shapes linkage synthesis is asked for, drawn in
code as point lists (closed curves, counter-clockwise, evenly spaced in their parameter).

| name | what it is |
|---|---|
| `ellipse` | an ellipse of axes 2:1, the easiest coupler curve |
| `bean` | a kidney: one concave side (a classic four-bar coupler shape) |
| `teardrop` | a drop with one sharp end, a cusp-like turn coupler curves make near dead centres |
| `crescent` | a banana: two near-parallel arcs joined by tight turns |
| `figure_eight` | a lemniscate of Gerono: the curve crosses itself |
| `letter_d` | a D: a straight stem and a half-ellipse bowl, meeting at two right angles |
| `rounded_triangle` | a triangle with rounded corners and straight sides |
| `gait` | a walking foot's path: a long flat stride on the ground and a lifted return arc |

`placed` puts a curve in a random frame (turned, scaled, moved), as a user draws anywhere.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.kinematics.paths import even_along

#: Points per target curve: about as dense as a mouse stroke the studio records, and dense
#: enough that the point-sampled chamfer of an exact fit is small (see bench.synthesis).
TARGET_POINTS = 400


def _polyline_loop(corners: np.ndarray, radius: float, count: int) -> np.ndarray:
    """A closed polygon whose corners are rounded with arcs of `radius`, sampled at `count`
    points evenly spaced along its length."""
    pieces = []
    n = len(corners)
    for i in range(n):
        before, at, after = corners[i - 1], corners[i], corners[(i + 1) % n]
        a = (before - at) / np.linalg.norm(before - at)
        b = (after - at) / np.linalg.norm(after - at)
        half = np.arccos(np.clip(a @ b, -1, 1)) / 2
        cut = radius / np.tan(half)  # where the arc meets each side
        centre = at + (a + b) / np.linalg.norm(a + b) * radius / np.sin(half)
        start, end = at + a * cut, at + b * cut
        first = np.arctan2(*(start - centre)[::-1])
        last = np.arctan2(*(end - centre)[::-1])
        sweep = (last - first + np.pi) % (2 * np.pi) - np.pi
        angles = first + sweep * np.linspace(0, 1, 16)
        pieces.append(centre + radius * np.column_stack([np.cos(angles), np.sin(angles)]))
    return even_along(np.concatenate(pieces), count)


def target_curves(points: int = TARGET_POINTS) -> dict[str, np.ndarray]:
    """The bench's target curves by name, each (points, 2), in their own frame."""
    t = np.linspace(0, 2 * np.pi, points, endpoint=False)
    bowl = np.linspace(-np.pi / 2, np.pi / 2, 100, endpoint=False)
    gait_stride = np.linspace(-1, 1, points // 2, endpoint=False)
    gait_lift = np.linspace(0, np.pi, points - points // 2, endpoint=False)
    return {
        "ellipse": np.column_stack([np.cos(t), 0.5 * np.sin(t)]),
        "bean": np.column_stack(
            [(1 + 0.35 * np.cos(t)) * np.cos(t), 0.7 * np.sin(t) + 0.25 * np.sin(2 * t)]
        ),
        "teardrop": np.column_stack([np.cos(t), np.sin(t) * np.sin(t / 2) ** 2]),
        "crescent": np.column_stack([np.cos(t), 0.15 * np.sin(t) + 0.45 * np.cos(t) ** 2]),
        "figure_eight": np.column_stack([np.sin(t), np.sin(t) * np.cos(t)]),
        "letter_d": even_along(
            np.concatenate(
                [
                    np.column_stack([np.zeros(50), np.linspace(1, -1, 50, endpoint=False)]),
                    np.column_stack([0.9 * np.cos(bowl), np.sin(bowl)]),
                ]
            ),
            points,
        ),
        "rounded_triangle": _polyline_loop(
            np.array([[-1.0, -0.6], [1.0, -0.6], [0.0, 1.1]]), 0.25, points
        ),
        "gait": np.concatenate(
            [
                np.column_stack([gait_stride, np.zeros_like(gait_stride)]),
                np.column_stack([np.cos(gait_lift), 0.35 * np.sin(gait_lift)]),
            ]
        ),
    }


def placed(curve: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`curve` turned by a random angle, scaled by 0.5 to 50 and moved up to 100 away."""
    angle = rng.uniform(0, 2 * np.pi)
    turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    scale = 10 ** rng.uniform(np.log10(0.5), np.log10(50))
    return curve @ turn.T * scale + rng.uniform(-100, 100, 2)
