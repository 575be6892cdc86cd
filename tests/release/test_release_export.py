"""The release's curve rules (`release.format`) on hand-made curves with known answers, and
`links export-dataset --format release` read back by `release_reader`, a reader written from
the release's published facts alone (it imports numpy and pickle only)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import links_ray
from links_ray.data.curation import KEEP_SHARE, keep_draw, path_ids
from links_ray.engine.kinematics.mechanism import ACTUATED, FIXED, SIMPLE
from links_ray.engine.kinematics.sampling import PositionSampler
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.topology import grow_topology
from links_ray.release.exporter import export_release
from links_ray.release.format import (
    RELEASE_CIRCLE_VARIANCE,
    release_arcs,
    release_circle_variance,
    release_circles,
    release_normalize,
    release_normalize_many,
    release_trajectories,
    release_trajectories_many,
)
from tests.cli.test_export_dataset import BARE_PLAN, _write
from tests.support.cli import links
from tests.support.release_reader import ANGLES as T
from tests.support.release_reader import normalize, read_batches, simulate

NAMES = ("dataset", "simulation_dataset", "normalized_dataset", "curated_dataset")


def turned(curve: np.ndarray, angle: float, scale: float, shift: tuple[float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return scale * curve @ np.array([[c, s], [-s, c]]) + np.asarray(shift)


# -- the rules on hand-made curves ---------------------------------------------------------


@pytest.mark.parametrize("first", [0, 13, 40])
def test_an_ellipse_lies_along_x_in_the_unit_width(first: int) -> None:
    """An ellipse of semi-axes 2 and 1, sampled at both ends of its major axis, turned:
    it becomes one of semi-axes 0.5 and 0.25 centred at (0.5, 0.25). Its point 0 is at the
    `first`-th of 200 even steps from the major axis: when not on it, the first hop does not
    reach the longest chord and a further one must."""
    t = (np.arange(200) + first) * (2.0 * np.pi / 200)
    ellipse = np.stack([2.0 * np.cos(t), np.sin(t)], axis=1)
    out = release_normalize(turned(ellipse, 0.9, 1.5, (1.0, 2.0)))
    assert out.min(axis=0) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert out.max(axis=0) == pytest.approx([1.0, 0.5], abs=1e-12)
    radius = ((out[:, 0] - 0.5) / 0.5) ** 2 + ((out[:, 1] - 0.25) / 0.25) ** 2
    np.testing.assert_allclose(radius, 1.0, atol=1e-12)


@pytest.mark.parametrize(
    ("angle", "scale", "shift"),
    [(0.7, 3.0, (5.0, -2.0)), (2.9, 0.2, (-1.0, 4.0)), (-1.3, 1, (0, 0))],
)
def test_a_turned_scaled_and_shifted_ellipse_normalizes_as_the_upright_one(
    angle: float, scale: float, shift: tuple[float, float]
) -> None:
    """The same curve however placed: the upright ellipse's normalization, or (the scale
    moves x = 0.5 within the curve, so the choice may differ) that turned 180 degrees."""
    ellipse = np.stack([2.0 * np.cos(T), np.sin(T)], axis=1)
    upright = release_normalize(ellipse)
    half_turn = np.stack([1.0 - upright[:, 0], upright[:, 1].max() - upright[:, 1]], axis=1)
    out = release_normalize(turned(ellipse, angle, scale, shift))
    assert min(np.abs(out - upright).max(), np.abs(out - half_turn).max()) < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1.0, 2.0, np.pi, -2.5])
def test_of_the_two_turns_the_one_lower_at_the_middle_is_kept(angle: float) -> None:
    """A dome of width 1 traced there and back: its longest chord is its base. Up, its points
    nearest x = 0.5 are 0.3 high; turned over they are at 0: the dome is kept upside down,
    however the curve came, and that turned-over dome is computed here by hand."""
    x = (1.0 - np.cos(T)) / 2.0
    width = x.max()
    dome = np.stack([x, 0.3 * np.sin(np.pi * x / width)], axis=1)
    top = dome[:, 1].max()
    by_hand = np.stack([width - x, top - dome[:, 1]], axis=1) / width
    out = release_normalize(turned(dome, angle, 1.0, (2.0, -7.0)))
    np.testing.assert_allclose(out, by_hand, atol=1e-9)
    middle = np.argsort(np.abs(out[:, 0] - 0.5))[:5]
    assert np.all(out[middle, 1] < 0.01)


@pytest.fixture(scope="module")
def generated_curves() -> np.ndarray:
    """(P, 200, 2) float32: every moving joint's path at the release's angles of 8 mechanisms
    each of 60 generated topologies of 6 to 12 joints, rounded as the release's files hold
    them: some 3,000 curves, a few dozen of them circles whose two turns tie."""
    rng = np.random.default_rng(39)
    curves = []
    for t in range(60):
        topology = grow_topology(rng, 6 + 2 * (t % 4))
        simulator = TopologySimulator.from_topology(topology)
        positions = PositionSampler(simulator, 200).search(8, rng).positions
        count = len(positions)
        trajectories, locks = release_trajectories_many(
            np.stack([topology.adjacency] * count),
            np.stack([topology.node_types] * count),
            positions.astype(np.float32),
        )
        moving = topology.node_types != FIXED
        curves += [path for path in trajectories[locks < 0][:, moving].reshape(-1, 200, 2)]
    return np.stack(curves).astype(np.float32)


def test_the_turn_follows_the_release_on_thousands_of_generated_curves(
    generated_curves: np.ndarray,
) -> None:
    """links-ray's normalization against the reader's restatement of the release's rule
    (`release_reader.normalize`), curve by curve; the rule links-ray once followed (the mean
    height, not the highest) disagrees on some of the same curves, so this test tells them
    apart."""
    assert len(generated_curves) >= 2500
    ours = release_normalize_many(generated_curves)
    theirs = np.stack([normalize(curve) for curve in generated_curves])
    differ = np.flatnonzero(~np.isclose(ours, theirs, rtol=0, atol=1e-4).all(axis=(1, 2)))
    assert differ.size == 0, f"{differ.size} curves differ, the first {differ[:10].tolist()}"
    by_mean = np.stack([normalize(curve, np.mean) for curve in generated_curves[:1000]])
    assert (~np.isclose(by_mean, theirs[:1000], rtol=0, atol=1e-4).all(axis=(1, 2))).sum() > 10


def test_a_curve_with_nan_or_no_extent_becomes_zeros() -> None:
    ellipse = np.stack([2.0 * np.cos(T), np.sin(T)], axis=1)
    broken = ellipse.copy()
    broken[17, 1] = np.nan
    still = np.tile([3.0, 4.0], (200, 1))
    out = release_normalize_many(np.stack([broken, ellipse, still]))
    assert np.array_equal(out[0], np.zeros((200, 2)))
    assert np.array_equal(out[2], np.zeros((200, 2)))
    np.testing.assert_array_equal(out[1], release_normalize(ellipse))


def test_circle_variance_of_known_curves() -> None:
    """Distances from (0.5, 0.5) of 0.4 and 0.6 alternately: variance 0.01. A circle of any
    size and place normalizes to radius 0.5 about (0.5, 0.5): variance about 0."""
    radii = np.where(np.arange(200) % 2 == 0, 0.4, 0.6)
    star = 0.5 + radii[:, None] * np.stack([np.cos(T), np.sin(T)], axis=1)
    assert release_circle_variance(star) == pytest.approx(0.01, rel=1e-12)
    circle = turned(np.stack([np.cos(T), np.sin(T)], axis=1), 0.4, 7.0, (3.0, 1.0))
    assert release_circle_variance(release_normalize(circle)) < 1e-8
    both = release_circle_variance(np.stack([star, star]))
    np.testing.assert_allclose(both, [0.01, 0.01], rtol=1e-12)


def test_arcs_first_then_circles() -> None:
    """A six-bar: 0 and 2 fixed, 1 the crank's tip, 3 on 1 and 2, 4 on 1 and 3, 5 on 3 and 4.
    The crank's tip and 3 are arcs; a circle's curve is a circle only if not an arc."""
    adjacency = np.zeros((6, 6), dtype=bool)
    for a, b in [(0, 1), (1, 3), (2, 3), (1, 4), (3, 4), (3, 5), (4, 5)]:
        adjacency[a, b] = adjacency[b, a] = True
    fixed = np.array([True, False, True, False, False, False])
    assert release_arcs(adjacency, fixed).tolist() == [False, True, False, True, False, False]
    two = release_arcs(np.stack([adjacency, adjacency]), np.stack([fixed, fixed]))
    assert two.shape == (2, 6) and two[1, 3]
    circle = release_normalize(np.stack([np.cos(T), np.sin(T)], axis=1))
    ellipse = release_normalize(np.stack([2.0 * np.cos(T), np.sin(T)], axis=1))
    curves = np.stack([circle, circle, ellipse, ellipse])
    is_arc = np.array([True, False, True, False])
    assert release_circles(curves, is_arc).tolist() == [False, True, False, False]
    assert release_circle_variance(ellipse) > RELEASE_CIRCLE_VARIANCE


# -- the files, read by a reader of the release's own (release_reader) -------------------


@pytest.mark.parametrize("crank_angle", [0.0, 1.0, -2.2])
def test_the_release_angles_are_absolute_whatever_the_crank_starts_at(crank_angle: float) -> None:
    """A crank-rocker four-bar (0 and 2 fixed, 1 the crank's tip, 3 on 1 and 2) turned by
    `crank_angle` about joint 0: links-ray's solver at the release's angles places joint 1
    along +x first, as the reader's own circle intersections do."""
    adjacency = np.zeros((4, 4), dtype=np.uint8)
    for a, b in [(0, 1), (1, 3), (2, 3)]:
        adjacency[a, b] = adjacency[b, a] = 1
    node_types = np.array([FIXED, ACTUATED, FIXED, SIMPLE], dtype=np.int8)
    upright = np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [2.5, 2.0]])
    positions = turned(upright, -crank_angle, 1.0, (0.4, -0.3))
    truth = simulate(adjacency.astype(bool), positions, node_types == FIXED)
    assert truth is not None
    np.testing.assert_allclose(truth[1, 0] - truth[0, 0], [1.0, 0.0], atol=1e-12)
    one, lock = release_trajectories(adjacency, node_types, positions)
    assert lock == (-1, -1)
    np.testing.assert_allclose(one, truth, atol=1e-9)
    many, locks = release_trajectories_many(
        np.stack([adjacency] * 2), np.stack([node_types] * 2), np.stack([positions, upright])
    )
    assert locks.tolist() == [-1, -1]
    np.testing.assert_array_equal(many[0], one)


def read_export(out: Path) -> dict[str, list[list]]:
    files = {name: read_batches(out / name) for name in NAMES}
    assert {p.name for p in out.iterdir()} == set(NAMES)
    assert len({len(batches) for batches in files.values()}) == 1
    return files


def check_export(root: str, out: Path, chunk_size: int) -> list[set[tuple[int, int]]]:
    """Everything a release reader can check against the root; returns, per batch, the
    (mechanism_id, joint) pairs of the curated curves."""
    files = read_export(out)
    mechanisms = links_ray.load(root, "mechanisms", reshape=True).sort_values("mechanism_id")
    ids = mechanisms["mechanism_id"].to_numpy()
    sizes = [len(batch) for batch in files["dataset"]]
    assert sum(sizes) == len(ids) and all(size == chunk_size for size in sizes[:-1])
    assert 0 < sizes[-1] <= chunk_size
    curated = []
    row = 0
    for k, batch in enumerate(files["dataset"]):
        stored = mechanisms.iloc[row : row + len(batch)]
        joint_counts = set()
        trajectories = {}
        for entry, (_, truth) in zip(batch, stored.iterrows(), strict=True):
            assert isinstance(entry, list) and len(entry) == 3
            a, x0, node_type = entry
            assert a.dtype == bool and x0.dtype == np.float32 and node_type.dtype == bool
            assert np.array_equal(a, truth["adjacency"].astype(bool))
            assert np.array_equal(x0, truth["positions"].astype(np.float32))
            assert np.array_equal(node_type, truth["node_types"] == FIXED)
            assert node_type[0] and not node_type[1]
            joint_counts.add(len(x0))
        for x_sol, j in files["simulation_dataset"][k]:
            assert type(j) is int
            mine = simulate(*batch[j])
            assert mine is not None and x_sol.shape == mine.shape
            np.testing.assert_allclose(x_sol, mine, rtol=0, atol=2e-5)
            trajectories[j] = x_sol
        # links-ray's mechanisms turn fully: every one has its simulation.
        assert sorted(trajectories) == list(range(len(batch)))
        moving = {(j, node) for j in range(len(batch)) for node in np.flatnonzero(~batch[j][2])}
        normalized = {}
        for curve, j, node in files["normalized_dataset"][k]:
            assert curve.shape == (200, 2) and type(j) is int and type(node) is int
            np.testing.assert_allclose(curve, normalize(trajectories[j][node]), atol=2e-6)
            normalized[j, node] = curve
        assert set(normalized) == moving
        pairs = set()
        for curve, j, node in files["curated_dataset"][k]:
            assert np.array_equal(curve, normalized[j, node])
            pairs.add((int(ids[row + j]), node))
        curated.append(pairs)
        row += len(batch)
    return curated


@pytest.fixture(scope="module")
def bare_root(tmp_path_factory: pytest.TempPathFactory) -> str:
    return _write(str(tmp_path_factory.mktemp("release") / "bare"), BARE_PLAN)


def test_a_generated_and_curated_root_reads_as_the_release(dataset: str, tmp_path: Path) -> None:
    """300 mechanisms of 60 topologies, shards of 10 topologies of one joint count: the batches
    of 64 draw on shards of several joint counts at once. The curated curves are the root's
    `curated` table, pair for pair."""
    out = tmp_path / "release"
    summary = export_release(dataset, str(out), chunk_size=64, format="release")
    assert summary["mechanisms"] == 300 and summary["locked"] == 0
    assert summary["seeded_shards"] == 0
    curated = check_export(dataset, out, 64)
    files = read_export(out)
    assert max(len({len(e[1]) for e in batch}) for batch in files["dataset"]) > 1
    truth = links_ray.load(dataset, "curated", columns=["mechanism_id", "joint"])
    pairs = set(zip(truth["mechanism_id"].tolist(), truth["joint"].tolist(), strict=True))
    assert set().union(*curated) == pairs and sum(map(len, curated)) == len(pairs)
    assert summary["curated"] == len(pairs)


def test_a_root_never_curated_gets_the_seeded_choice_on_the_release_classes(
    bare_root: str, tmp_path: Path
) -> None:
    """Every curve neither an arc (its joint linked to a fixed one) nor, then, a circle (the
    reader's own normalization and variance) is curated; of the others, exactly those whose
    seeded draw (seed 0) falls under the kept share."""
    out = tmp_path / "release"
    summary = export_release(bare_root, str(out), chunk_size=8, format="release")
    assert summary["mechanisms"] == 45 and summary["seeded_shards"] > 0
    curated = set().union(*check_export(bare_root, out, 8))
    files = read_export(out)
    ids = np.sort(links_ray.load(bare_root, "mechanisms")["mechanism_id"].to_numpy())
    common, rare = set(), set()
    for k, batch in enumerate(files["dataset"]):
        for curve, j, node in files["normalized_dataset"][k]:
            a, _, fixed = batch[j]
            arc = bool(np.any(a[node] & fixed))
            radii = np.linalg.norm(curve.astype(np.float64) - 0.5, axis=1)
            circle = not arc and radii.var() < 5e-4
            pair = (int(ids[8 * k + j]), node)
            (rare if arc or circle else common).add(pair)
    assert common and rare
    lucky = {
        pair
        for pair in rare
        if keep_draw(path_ids(np.array([pair[0]]), np.array([pair[1]])), 0)[0] < KEEP_SHARE
    }
    assert curated == common | lucky


def test_the_command_writes_the_four_files(bare_root: str, tmp_path: Path) -> None:
    out = tmp_path / "release"
    result = links("export-dataset", bare_root, "--out", str(out), "--format", "release")
    assert result.returncode == 0, result.stderr
    assert "45 mechanisms" in result.stdout and "batches of the release's files" in result.stdout
    files = read_export(out)
    assert len(files["dataset"]) == 1 and len(files["dataset"][0]) == 45


def test_a_bad_format_is_one_line(bare_root: str, tmp_path: Path) -> None:
    result = links("export-dataset", bare_root, "--out", str(tmp_path / "o"), "--format", "csv")
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and "--format" in result.stderr
    assert not (tmp_path / "o").exists()
    with pytest.raises(ValueError, match="format must be one of numpy, release"):
        export_release(bare_root, str(tmp_path / "o"), format="csv")


def test_a_mechanism_that_locks_keeps_only_its_dataset_entry(
    bare_root: str, tmp_path: Path
) -> None:
    """Mechanism 0's crank made five times longer (its shard's file rewritten): it cannot turn
    (the reader's own solver says so), and, as in the release, it is in `dataset` with no
    simulation and no curve; every other mechanism is whole."""
    root = tmp_path / "root"
    shutil.copytree(bare_root, root)
    (path,) = [
        p for p in root.rglob("*.parquet") if 0 in pq.read_table(p)["mechanism_id"].to_pylist()
    ]
    table = pq.read_table(path)
    rows = table.to_pylist()
    n = len(rows[0]["node_types"])
    positions = np.asarray(rows[0]["positions"]).reshape(n, 2)
    positions[1] = positions[0] + 5.0 * (positions[1] - positions[0])
    rows[0]["positions"] = positions.ravel().tolist()
    pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path)

    out = tmp_path / "release"
    summary = export_release(str(root), str(out), chunk_size=8, format="release")
    assert summary["mechanisms"] == 45 and summary["locked"] == 1
    files = read_export(out)
    first = files["dataset"][0]
    assert simulate(*first[0]) is None
    assert np.array_equal(first[0][1], positions.astype(np.float32))
    assert sorted(j for _, j in files["simulation_dataset"][0]) == list(range(1, len(first)))
    for name in ("normalized_dataset", "curated_dataset"):
        assert all(j != 0 for _, j, _ in files[name][0])
    assert {j for _, j, _ in files["normalized_dataset"][0]} == set(range(1, len(first)))


def test_one_split(bare_root: str, tmp_path: Path) -> None:
    out = tmp_path / "release"
    summary = export_release(bare_root, str(out), chunk_size=4, split="train", format="release")
    train = links_ray.load(bare_root, "mechanisms", split="train", reshape=True)
    train = train.sort_values("mechanism_id")
    exported = [entry for batch in read_export(out)["dataset"] for entry in batch]
    assert 0 < len(exported) == len(train) == summary["mechanisms"] < 45
    for (a, x0, _), (_, truth) in zip(exported, train.iterrows(), strict=True):
        assert np.array_equal(x0, truth["positions"].astype(np.float32))
        assert np.array_equal(a, truth["adjacency"].astype(bool))
