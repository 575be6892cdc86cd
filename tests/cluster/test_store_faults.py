"""Faults of the store itself: the S3 server goes away in the middle of a run and comes back.

A generation run writes into a SeaweedFS of its own (`restartable_s3_server`). Once its first
shards have committed, the server is stopped by its PID, kept down for DOWN_S seconds and
started again on the same data folder and ports. The run must then finish with exactly the
rows of an undisturbed local run of the same plan.

Ray's workers take the environment of the process that started the cluster (`ray_cluster`),
and that points them at the session's server. So the run gets a driver of its own, joined to
the same cluster with a job-level `runtime_env` that sets AWS_ENDPOINT_URL to the private
server for that job's actors. Both servers accept the same credentials (the private one reads
the session's identity file), so the endpoint is all that differs and no key goes into the
runtime_env.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import boto3
import pyarrow as pa
import pytest

import links_ray
from links_ray.cluster.generation import generate

TABLES = ("mechanisms", "simulations", "negatives")
#: The plan: many small shards, so S3 round trips, not the engine, set the run's length and
#: most of it is still to do when the server goes away.
MECHANISMS, SEED, TOPOLOGIES_PER_SHARD = 2_000, 11, 2
#: How long the server stays down.
DOWN_S = 20.0
#: Limits of the waits; a run that needs longer has failed.
FIRST_COMMIT_TIMEOUT_S, RUN_TIMEOUT_S = 180.0, 600.0

#: The run's own driver: joins the cluster with the private endpoint for this job's workers.
DRIVER = """
import json, sys
import ray
from links_ray.cluster.generation import generate

address, endpoint, out, mechanisms, seed, per_shard = sys.argv[1:]
ray.init(
    address=address,
    runtime_env={"env_vars": {"AWS_ENDPOINT_URL": endpoint}},
    logging_level="WARNING",
)
summary = generate(
    out, int(mechanisms), seed=int(seed), progress=False, topologies_per_shard=int(per_shard)
)
print(json.dumps(summary))
"""


def committed_rows(uri: str) -> int:
    """Rows of `mechanisms` that `load` sees (committed ones only); 0 before there are any."""
    try:
        return links_ray.load(uri, "mechanisms", columns=["mechanism_id"], format="arrow").num_rows
    except ValueError:  # no table yet
        return 0


def read(uri: str) -> dict[str, pa.Table]:
    """Every generation table at `uri`, columns in name order, rows by mechanism_id."""
    tables = {}
    for table in TABLES:
        rows = links_ray.load(uri, table, format="arrow").sort_by("mechanism_id")
        tables[table] = rows.select(sorted(rows.column_names))
    return tables


def tail(path: Path, lines: int = 30) -> str:
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


def test_generation_outlives_an_s3_restart(
    ray_cluster: str,
    s3_env: str,
    restartable_s3_server: Any,
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    server = restartable_s3_server
    begin = time.monotonic()
    reference = str(tmp_path / "reference")
    generate(
        reference, MECHANISMS, seed=SEED, progress=False, topologies_per_shard=TOPOLOGIES_PER_SHARD
    )
    reference_s = time.monotonic() - begin

    # From here on this process, and the driver it starts, talk to the private server.
    monkeypatch.setenv("AWS_ENDPOINT_URL", server.endpoint)
    bucket = s3_env.removeprefix("s3://")
    boto3.session.Session().client("s3").create_bucket(Bucket=bucket)
    uri = f"{s3_env}/links"

    out, err = tmp_path / "driver.out", tmp_path / "driver.err"
    args = [ray_cluster, server.endpoint, uri, MECHANISMS, SEED, TOPOLOGIES_PER_SHARD]
    start = time.monotonic()
    with open(out, "wb") as stdout, open(err, "wb") as stderr:
        driver = subprocess.Popen(
            [sys.executable, "-c", DRIVER, *map(str, args)], stdout=stdout, stderr=stderr
        )
    try:
        rows = 0
        while not rows and driver.poll() is None:
            assert time.monotonic() - start < FIRST_COMMIT_TIMEOUT_S, "no shard committed"
            time.sleep(0.2)
            rows = committed_rows(uri)
        assert driver.poll() is None, f"the run ended before the fault:\n{tail(err)}"
        assert rows < MECHANISMS
        first_commit_s = time.monotonic() - start

        stopped_pid = server.pid
        server.stop()
        stopped = time.monotonic()
        time.sleep(DOWN_S)
        ready_s = server.start()
        down_s = time.monotonic() - stopped

        returncode = driver.wait(timeout=RUN_TIMEOUT_S)
    finally:
        if driver.poll() is None:
            driver.kill()
            driver.wait()
    print(
        f"\nreference run {reference_s:.1f} s; S3 run: {rows} rows after {first_commit_s:.1f} s, "
        f"server (pid {stopped_pid}) down {down_s:.1f} s, answering again {ready_s:.1f} s "
        f"after its restart, run done after {time.monotonic() - start:.1f} s"
    )
    assert returncode == 0, f"the run did not outlive the restart:\n{tail(err)}"
    summary = json.loads(out.read_text().splitlines()[-1])
    assert summary["complete"] and summary["rows"]["mechanisms"] == MECHANISMS
    got, want = read(uri), read(reference)
    for table in TABLES:
        assert got[table].equals(want[table]), f"{table} differs from the undisturbed run"
