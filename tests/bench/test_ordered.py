"""The ordered distance (links_ray.bench.ordered) against brute force: every start and both
directions tried in numpy, and the cases it is for."""

from __future__ import annotations

import numpy as np
import pytest

from links_ray.bench.ordered import OVERSAMPLE, ordered_match
from links_ray.engine.kinematics.paths import chamfer, even_along


def brute_force(drawn: np.ndarray, path: np.ndarray) -> tuple[float, int, int]:
    """(rms, start, direction) of the least mean squared distance, every start of the path
    resampled at OVERSAMPLE times the drawing's points, forward then backward, lowest first."""
    t = len(drawn)
    even = even_along(path, t * OVERSAMPLE, closed=True)
    best = (np.inf, 0, 1)
    for direction in (1, -1):
        for start in range(t * OVERSAMPLE):
            index = (start + direction * OVERSAMPLE * np.arange(t)) % (t * OVERSAMPLE)
            mean = float(np.mean(np.sum((drawn - even[index]) ** 2, axis=1)))
            if mean < best[0]:
                best = (mean, start, direction)
    return float(np.sqrt(best[0])), best[1], best[2]


def eight(count: int, phase: float = 0.0) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, count, endpoint=False) + phase
    return np.column_stack([np.sin(t), 0.6 * np.sin(2 * t)])


@pytest.mark.parametrize("seed", range(6))
def test_ordered_match_is_brute_forces(seed: int) -> None:
    rng = np.random.default_rng(seed)
    drawn = even_along(eight(300) + rng.normal(scale=0.05, size=(300, 2)), 40)
    path = eight(90, phase=rng.uniform(0, 6)) * rng.uniform(0.8, 1.2)
    if seed % 2:
        path = path[::-1]  # the path runs the other way round
    match = ordered_match(drawn, path)
    rms, start, direction = brute_force(drawn, path)
    assert match.distance == pytest.approx(rms, rel=1e-9)
    assert (match.start, match.direction) == (start, direction)
    assert match.direction == (-1 if seed % 2 else 1)


def test_order_tells_a_figure_eight_from_its_outline() -> None:
    """An eight and the same points traced as two separate loops' outline (its lobes in another
    order) are near in chamfer, far in order: the order is what a crossing curve adds."""
    drawn = even_along(eight(400), 100)
    lobes = eight(400)
    # The left lobe traced against the way the eight runs it: same points, another order.
    left = lobes[:, 0] < 0
    other = np.concatenate([lobes[~left], lobes[left][::-1]])
    assert chamfer(drawn, other) < 0.03
    assert ordered_match(drawn, eight(400)).distance < 0.01
    assert ordered_match(drawn, other).distance > 0.1


def test_bad_input_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match="drawn must have shape"):
        ordered_match(np.zeros((2, 2)), eight(10))
    with pytest.raises(ValueError, match="path must be finite"):
        ordered_match(eight(10), np.full((10, 2), np.nan))
