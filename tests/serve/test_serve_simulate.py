"""POST /api/simulate over real HTTP: the engine's trajectories, bit for bit, and a mechanism that
locks answered 422 with the step and joint where it does (the `client` fixture's app)."""

import numpy as np
import pytest

import links_ray
from tests.support.fourbars import stretched_four_bar, window_slack
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client, post_ok


@pytest.mark.parametrize("steps", [None, 50, 1])
def test_simulate_matches_the_engine(client: Client, steps: int | None) -> None:
    body = FOUR_BAR if steps is None else {**FOUR_BAR, "steps": steps}
    _, data = post_ok(client, "/api/simulate", body)
    expected = links_ray.simulate(
        FOUR_BAR["adjacency"], FOUR_BAR["node_types"], FOUR_BAR["positions"], steps or 200
    )
    got = np.array(data["trajectories"])
    assert got.shape == expected.shape == (4, steps or 200, 2)
    np.testing.assert_array_equal(got, expected)  # JSON round-trips float64 exactly


def test_simulate_locking_is_422_with_step_and_node(client: Client) -> None:
    with pytest.raises(links_ray.LockingError) as locked:
        links_ray.simulate(**LOCKING_FOUR_BAR)
    status, data = client.post("/api/simulate", LOCKING_FOUR_BAR)
    assert status == 422
    assert data == {"error": "locking", "step": locked.value.step, "node": locked.value.node}


def test_simulate_locking_between_steps_is_422(client: Client) -> None:
    """A four-bar that assembles at all 200 steps but locks between steps 37 and 38."""
    four_bar = stretched_four_bar(37, 200, window_slack(200))
    body = {name: value.tolist() for name, value in four_bar.items()}
    status, data = client.post("/api/simulate", body)
    assert status == 422
    assert data == {"error": "locking", "step": 38, "node": 3}
