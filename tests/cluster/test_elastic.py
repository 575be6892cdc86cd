"""The generator pool follows the cluster: it grows when a node joins and finishes the run when
that node leaves mid-run, with exactly the rows of an undisturbed run.

The cluster is real (Ray's multi-node test cluster: a head and a second raylet on this
machine), in a child process because this process already hosts the session's Ray.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from links_ray.cluster.generation import generate
from tests.cluster.test_generation import assert_same_rows, read_all

SCRIPT = r"""
import json, os, sys, threading, time
from pathlib import Path

import ray
from ray.cluster_utils import Cluster

from links_ray.cluster.generation import generate

out = sys.argv[1]
markers = Path(out) / "_links" / "shards"
cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
ray.init(address=cluster.address, logging_level="WARNING")
result = {}
thread = threading.Thread(
    target=lambda: result.update(
        generate(out, 12000, seed=5, progress=False, topologies_per_shard=1)
    )
)
thread.start()


def wait_for(condition, seconds):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not condition():
        time.sleep(0.05)
    return condition()


def committed():
    return len(list(markers.glob("*.json"))) if markers.exists() else 0


def running_generators():
    # Running: constructed (a generator waiting for a CPU, or still importing, is not).
    from ray._private import state

    actors = state.actors().values()
    return sum(a["ActorClassName"] == "GeneratorActor" and a["State"] == "ALIVE" for a in actors)


assert wait_for(lambda: committed() >= 2, 120), "the run started"
node = cluster.add_node(num_cpus=1)
grew = wait_for(lambda: running_generators() >= 2, 300)
at_join = committed()
wait_for(lambda: committed() >= at_join + 10, 60)
at_leave = committed()
cluster.remove_node(node)
thread.join()
print(json.dumps({"grew": grew, "at_leave": at_leave, "summary": result}))
ray.shutdown()
cluster.shutdown()
"""


def test_pool_grows_with_a_joining_node_and_survives_its_leaving(
    ray_cluster: str, tmp_path: Path
) -> None:
    out = tmp_path / "elastic"
    child = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(out)], capture_output=True, text=True, timeout=600
    )
    assert child.returncode == 0, child.stderr[-3000:]
    report = json.loads(child.stdout.strip().splitlines()[-1])
    summary = report["summary"]
    assert report["grew"], "a second actor runs on the new node"
    assert summary["workers"] == 2
    assert 0 < report["at_leave"] < summary["shards"], "the node left mid-run"
    assert summary["complete"] and summary["rows"]["mechanisms"] == 12000

    reference = tmp_path / "reference"
    generate(str(reference), 12000, seed=5, progress=False, topologies_per_shard=50)
    assert_same_rows(read_all(str(out)), read_all(str(reference)))
