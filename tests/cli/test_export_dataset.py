"""`links export-dataset`: the LINKS release layout, checked array by array against the
Parquet rows, re-simulation with `links_ray.simulate` and re-normalization with
`links_ray.normalize_path`; from a folder and from S3, with and without stored simulations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import links_ray
from links_ray.data.generation import GenerationPlan, write_shard
from links_ray.data.store import Store
from links_ray.engine.kinematics.paths import CIRCLE_VARIANCE_THRESHOLD
from links_ray.release.exporter import CURVE_SETS, export_release
from tests.support.cli import links

#: The root without simulations: generation's mechanisms only, never curated.
BARE_PLAN = GenerationPlan(seed=2, mechanisms=45, topologies_per_shard=2, tables=("mechanisms",))


def _write(uri: str, plan: GenerationPlan) -> str:
    store = Store.open(uri)
    for shard in plan.shards():
        write_shard(store, plan, shard)
    return uri


@pytest.fixture(scope="module")
def bare_root(tmp_path_factory: pytest.TempPathFactory) -> str:
    return _write(str(tmp_path_factory.mktemp("export") / "bare"), BARE_PLAN)


def read_export(out: Path) -> tuple[dict, list[dict[str, np.ndarray]]]:
    """The manifest, and each chunk's arrays by name."""
    manifest = json.loads((out / "manifest.json").read_text())
    chunks = [
        {f.stem: np.load(f) for f in (out / chunk["name"]).glob("*.npy")}
        for chunk in manifest["chunks"]
    ]
    return manifest, chunks


def check_layout(manifest: dict, chunks: list[dict[str, np.ndarray]], chunk_size: int) -> None:
    """Shapes and types; chunks of one joint count, full but the last of each joint count."""
    steps = manifest["steps"]
    sizes = [c["n_joints"] for c in manifest["chunks"]]
    assert sizes == sorted(sizes)
    for entry, arrays in zip(manifest["chunks"], chunks, strict=True):
        n, m = entry["n_joints"], entry["mechanisms"]
        assert 1 <= m <= chunk_size
        assert arrays["mechanism_id"].shape == arrays["topology_id"].shape == (m,)
        assert arrays["adjacency"].shape == (m, n, n) and arrays["adjacency"].dtype == np.uint8
        assert arrays["node_types"].shape == (m, n) and arrays["node_types"].dtype == np.int8
        assert arrays["positions"].shape == (m, n, 2) and arrays["positions"].dtype == np.float64
        assert arrays["simulations"].shape == (m, n, steps, 2)
        assert arrays["simulations"].dtype == np.float32
        assert np.all(np.diff(arrays["mechanism_id"]) > 0)
        for name in CURVE_SETS:
            p = entry[name]
            assert arrays[name].shape == (p, steps, 2) and arrays[name].dtype == np.float32
            assert arrays[f"{name}_mechanism"].shape == (p,)
            assert arrays[f"{name}_mechanism"].dtype == np.int32
            assert arrays[f"{name}_joint"].dtype == np.int8
            assert arrays[f"{name}_path_id"].dtype == np.int64
    for before, after in zip(manifest["chunks"], manifest["chunks"][1:], strict=False):
        if before["n_joints"] == after["n_joints"]:
            assert before["mechanisms"] == chunk_size


def check_curves(chunks: list[dict[str, np.ndarray]]) -> None:
    """Each curve's indices name its mechanism's row and joint (path_id = 32 mechanism_id +
    joint), a moving joint; normalizing the exported simulation of that joint gives it."""
    for arrays in chunks:
        for name in CURVE_SETS:
            rows, joints = arrays[f"{name}_mechanism"], arrays[f"{name}_joint"]
            path_ids = arrays[f"{name}_path_id"]
            assert np.array_equal(arrays["mechanism_id"][rows], path_ids >> 5)
            assert np.array_equal(joints, path_ids & 31)
            assert np.all(arrays["node_types"][rows, joints] != 0)
            for k in range(len(rows)):
                traced = arrays["simulations"][rows[k], joints[k]].astype(np.float64)
                normalized = links_ray.normalize_path(traced)
                np.testing.assert_allclose(arrays[name][k], normalized, atol=2e-6)


def stacked(chunks: list[dict[str, np.ndarray]], name: str) -> np.ndarray:
    return np.concatenate([c[name] for c in chunks])


def test_export_of_a_generated_and_curated_dataset(dataset: str, tmp_path: Path) -> None:
    """The Ray-made dataset of 300 mechanisms (50 a shard), in chunks of 7: chunks cross
    shards. Every array equals its Parquet rows."""
    out = tmp_path / "release"
    manifest = export_release(dataset, str(out), chunk_size=7)
    assert manifest == json.loads((out / "manifest.json").read_text())
    manifest, chunks = read_export(out)
    check_layout(manifest, chunks, 7)
    assert manifest["mechanisms"] == 300 and manifest["resimulated"] == 0

    mechanisms = links_ray.load(dataset, "mechanisms", reshape=True).set_index("mechanism_id")
    simulations = links_ray.load(dataset, "simulations", reshape=True).set_index("mechanism_id")
    ids = stacked(chunks, "mechanism_id")
    assert sorted(ids) == sorted(mechanisms.index)
    for arrays in chunks:
        for row, mechanism_id in enumerate(arrays["mechanism_id"]):
            stored = mechanisms.loc[mechanism_id]
            assert arrays["topology_id"][row] == stored["topology_id"]
            assert np.array_equal(arrays["adjacency"][row], stored["adjacency"])
            assert np.array_equal(arrays["node_types"][row], stored["node_types"])
            assert np.array_equal(arrays["positions"][row], stored["positions"])
            trajectories = simulations.loc[mechanism_id, "trajectories"]
            assert np.array_equal(arrays["simulations"][row], trajectories)

    for name, table in (("normalized", "paths"), ("curated", "curated")):
        rows = links_ray.load(dataset, table, reshape=True).set_index("path_id")
        path_ids = stacked(chunks, f"{name}_path_id")
        assert sorted(path_ids) == sorted(rows.index) and manifest[name] == len(rows)
        points = stacked(chunks, name)
        for k in range(0, len(path_ids), 7):
            assert np.array_equal(points[k], rows.loc[path_ids[k], "points"])
    check_curves(chunks)


def test_export_without_simulations_simulates_again(bare_root: str, tmp_path: Path) -> None:
    """No simulations and no curation: simulations are those of `links_ray.simulate`, one
    normalized curve per moving joint, and curated keeps every curve that is neither an arc nor
    a circle (both judged here from the exported arrays)."""
    out = tmp_path / "release"
    export_release(bare_root, str(out), chunk_size=4)
    manifest, chunks = read_export(out)
    check_layout(manifest, chunks, 4)
    assert manifest["mechanisms"] == manifest["resimulated"] == 45
    mechanisms = links_ray.load(bare_root, "mechanisms", reshape=True).set_index("mechanism_id")
    moving = 0
    for arrays in chunks:
        for row, mechanism_id in enumerate(arrays["mechanism_id"]):
            stored = mechanisms.loc[mechanism_id]
            assert np.array_equal(arrays["positions"][row], stored["positions"])
            truth = links_ray.simulate(
                stored["adjacency"], stored["node_types"], stored["positions"]
            )
            assert np.array_equal(arrays["simulations"][row], truth.astype(np.float32))
            moving += int(np.sum(stored["node_types"] != 0))
        rows, joints = arrays["normalized_mechanism"], arrays["normalized_joint"]
        fixed = arrays["node_types"][rows] == 0
        is_arc = np.any(arrays["adjacency"][rows, joints].astype(bool) & fixed, axis=1)
        radii = np.linalg.norm(arrays["normalized"].astype(np.float64) - 0.5, axis=2)
        is_circle = radii.var(axis=1) < CIRCLE_VARIANCE_THRESHOLD
        rare = set(arrays["normalized_path_id"][is_arc | is_circle])
        common = set(arrays["normalized_path_id"][~(is_arc | is_circle)])
        curated = set(arrays["curated_path_id"])
        assert common <= curated <= common | rare
    assert manifest["normalized"] == moving
    assert manifest["curated"] < manifest["normalized"]
    check_curves(chunks)


def test_export_of_one_split(bare_root: str, tmp_path: Path) -> None:
    out = tmp_path / "release"
    manifest = export_release(bare_root, str(out), chunk_size=3, split="train")
    _, chunks = read_export(out)
    truth = links_ray.load(bare_root, "mechanisms", split="train")
    assert sorted(stacked(chunks, "mechanism_id")) == sorted(truth["mechanism_id"])
    assert 0 < manifest["mechanisms"] < 45 and manifest["split"] == "train"
    assert set(links_ray.split_of(stacked(chunks, "topology_id"))) == {"train"}
    check_curves(chunks)


def test_export_from_s3_equals_the_folders(s3_env: str, bare_root: str, tmp_path: Path) -> None:
    """The same plan written to S3 exports the same arrays as from the folder."""
    uri = _write(f"{s3_env}/bare", BARE_PLAN)
    export_release(bare_root, str(tmp_path / "folder"), chunk_size=5)
    manifest = export_release(uri, str(tmp_path / "s3"), chunk_size=5)
    assert manifest["source"] == uri
    _, from_folder = read_export(tmp_path / "folder")
    _, from_s3 = read_export(tmp_path / "s3")
    assert manifest["mechanisms"] == 45 and len(from_folder) == len(from_s3) >= 45 // 5
    for a, b in zip(from_folder, from_s3, strict=True):
        assert a.keys() == b.keys()
        for name in a:
            assert np.array_equal(a[name], b[name]), name


def test_the_command(bare_root: str, tmp_path: Path) -> None:
    out = tmp_path / "release"
    result = links("export-dataset", bare_root, "--out", str(out), "--chunk-size", "8", "--json")
    assert result.returncode == 0, result.stderr
    manifest = json.loads(result.stdout)
    assert manifest == json.loads((out / "manifest.json").read_text())
    assert manifest["mechanisms"] == 45 and manifest["chunk_size"] == 8
    again = links("export-dataset", bare_root, "--out", str(out))
    assert again.returncode == 2
    assert again.stderr.strip().endswith("is not an empty folder: export into a new or empty one")
    assert len(again.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"chunk_size": 0}, "chunk_size must be at least 1"),
        ({"split": "dev"}, "split must be one of"),
        ({"split": "test", "split_fractions": (0.5, 0.5, 0.5)}, "must sum to 1"),
    ],
)
def test_bad_arguments_are_value_errors(
    bare_root: str, tmp_path: Path, arguments: dict, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        export_release(bare_root, str(tmp_path / "out"), **arguments)
    assert not (tmp_path / "out").exists()


def test_a_root_without_mechanisms_is_a_value_error(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="holds no generated shards"):
        export_release(str(tmp_path / "empty"), str(tmp_path / "out"))


def test_a_lean_root_exports_the_arrays_of_a_stored_one(tmp_path: Path) -> None:
    """A root of mechanisms and curated ids (`links curate --store ids`) exports, array by
    array, what the same run curated with points and stored simulations exports."""
    from tests.support.local_dataset import stored_and_lean

    stored, lean = stored_and_lean(str(tmp_path), seed=4, mechanisms=30, topologies_per_shard=2)
    exports = {}
    for name, root in (("stored", stored), ("lean", lean)):
        export_release(root, str(tmp_path / f"{name}-release"), chunk_size=4)
        exports[name] = read_export(tmp_path / f"{name}-release")
    (stored_manifest, stored_chunks), (lean_manifest, lean_chunks) = exports.values()
    assert lean_manifest["chunks"] == stored_manifest["chunks"]
    assert lean_manifest["resimulated"] == 30 and stored_manifest["resimulated"] == 0
    for theirs, ours in zip(stored_chunks, lean_chunks, strict=True):
        assert theirs.keys() == ours.keys() and "curated" in ours
        for name, array in theirs.items():
            assert array.dtype == ours[name].dtype and array.tobytes() == ours[name].tobytes()
