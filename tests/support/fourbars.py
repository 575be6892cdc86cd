"""Four-bars in closed form whose crank turns, or locks, only between two sampled steps.

Joint 0 is the crank's centre (0.5, 0.5), joint 1 its tip (radius R = 0.05), joint 2 a fixed
pivot C at distance L from the centre, and joint 3 closes the loop: radius r1 to the tip and r2
to C. The tip is farthest from C, at L + R, when the crank points away from C; the coupler
stretches fully there if r1 + r2 = L + R. Pointing that angle midway between two of `steps`
sampled angles and setting r1 + r2 just below L + R makes a dyad that cannot be assembled only
in a window narrower than the steps around it: every sampled step assembles.
"""

import numpy as np

CENTRE, R, L = np.array([0.5, 0.5]), 0.05, 0.3
ADJACENCY = np.array([[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]])
NODE_TYPES = np.array([0, 2, 0, 1])


def farthest_angle(step: int, steps: int) -> float:
    """The crank angle midway between sampled steps `step` and `step` + 1."""
    return 2 * np.pi * (step + 0.5) / steps


def stretched_four_bar(step: int, steps: int, slack: float) -> dict:
    """The four-bar whose coupler reach r1 + r2 is L + R + slack, stretched fully (slack 0)
    midway between steps `step` and `step` + 1: negative slack locks there, only there."""
    away = farthest_angle(step, steps)
    pivot = CENTRE - L * np.array([np.cos(away), np.sin(away)])
    tip = CENTRE + np.array([R, 0.0])
    reach = L + R + slack
    r1 = r2 = reach / 2
    # Joint 3 where the two circles meet at the start, on the left of tip -> pivot.
    gap = pivot - tip
    d = np.hypot(*gap)
    along = (d * d + r1 * r1 - r2 * r2) / (2 * d)
    height = np.sqrt(r1 * r1 - along * along)
    joint = tip + along * gap / d + height * np.array([-gap[1], gap[0]]) / d
    positions = np.array([CENTRE, tip, pivot, joint])
    return {"adjacency": ADJACENCY, "node_types": NODE_TYPES, "positions": positions}


def window_slack(steps: int) -> float:
    """A slack whose lock window is half as wide as the steps are apart: the parents' distance
    at the nearest sampled angles is L + R - 2 * this (law of cosines)."""
    nearest = np.sqrt(L * L + R * R + 2 * L * R * np.cos(np.pi / steps))
    return -(L + R - nearest) / 2
