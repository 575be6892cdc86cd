"""The app's configuration: the args its builder takes, whether an app fits a Ray's CPUs and
memory, a replica keeping to the CPUs Ray gives it, and deploy/'s Serve config and RayService
manifest (tests/project/test_deploy_serve.py checks every deploy/ file against the code)."""

import importlib
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.support.serving import EXIT_S, curated_shards

REPO = Path(__file__).resolve().parents[2]


def test_app_builder_args(dataset: str, tmp_path: Path) -> None:
    from ray.serve.deployment import Application

    from links_ray.serve.app import app_builder, build_app

    assert isinstance(app_builder({"root": dataset, "replicas": "2"}), Application)
    sharded = {"shards": "3", "shard_cpus": "0.5", "shard_memory_gb": 2, "max_retrievals": 4}
    assert isinstance(app_builder({"root": dataset, **sharded}), Application)
    for bad, message in (
        ({}, "the links application needs args.root"),
        ({"root": ""}, "the links application needs args.root"),
        ({"root": str(tmp_path)}, "has no curated table"),
        (
            {"root": dataset, "replicas": "two"},
            "args.replicas must be a positive integer, got 'two'",
        ),
        ({"root": dataset, "replicas": True}, "args.replicas must be a positive integer, got True"),
        ({"root": dataset, "x": 1}, r"unknown args for the links application: \['x'\]"),
        ({"root": dataset, "shards": 0}, "args.shards must be a positive integer, got 0"),
        ({"root": dataset, "shards": 1.5}, "args.shards must be a positive integer, got 1.5"),
        (
            {"root": dataset, "shard_cpus": "nan"},
            "args.shard_cpus must be a positive number, got 'nan'",
        ),
        (
            {"root": dataset, "shard_memory_gb": -1},
            "args.shard_memory_gb must be a positive number, got -1",
        ),
        # One part more than the dataset's curated shards: the last one would be empty.
        (
            {"root": dataset, "shards": curated_shards(dataset) + 1},
            f"has {curated_shards(dataset)} curated shards: split in "
            f"{curated_shards(dataset) + 1} partitions, partition {curated_shards(dataset)} "
            "would have none; use a smaller --shards",
        ),
    ):
        with pytest.raises(ValueError, match=message):
            app_builder(bad)
    with pytest.raises(ValueError, match="replicas must be a positive integer, got 0"):
        build_app(dataset, replicas=0)
    with pytest.raises(ValueError, match="shard_cpus must be a positive number, got 0"):
        build_app(dataset, shards=2, shard_cpus=0)


def test_an_app_that_cannot_fit_is_refused() -> None:
    """On a Ray `links serve` starts itself, an app larger than the machine is refused in one
    line, where Serve would wait for resources forever."""
    from links_ray.serve.app import check_fits

    two_cpus = {"CPU": 2.0, "memory": 8e9}
    check_fits(1, None, 1.0, None, two_cpus)
    check_fits(1, 4, 0.25, 1.5, two_cpus)
    with pytest.raises(
        ValueError, match=r"the app needs 5 CPUs \(1 a gateway replica, 1 a partition"
    ):
        check_fits(1, 4, 1.0, None, two_cpus)
    with pytest.raises(
        ValueError, match=r"the partitions reserve 12\.0 GB and this Ray has 8\.0 GB"
    ):
        check_fits(1, 2, 0.5, 6, two_cpus)


def test_partitions_share_the_cpus_the_gateway_leaves() -> None:
    """On a Ray `links serve` started, shards given no CPUs reserve 1 each where that fits,
    else an equal share of what the gateway's replicas (one CPU each) leave, in Ray's steps of
    0.0001 CPU, and the app then fits; where nothing is left, a refusal naming why."""
    from links_ray.serve.app import check_fits, fit_partition_cpus

    for cpus, replicas, shards, share in (
        (8, 1, 2, 1.0),
        (3, 1, 2, 1.0),
        (2, 1, 2, 0.5),
        (2, 1, 4, 0.25),
        (2, 1, 3, 0.3333),
        (4, 2, 3, 0.3333),
        (1.5, 1, 2, 0.25),
    ):
        resources = {"CPU": float(cpus), "memory": 8e9}
        assert fit_partition_cpus(replicas, shards, resources) == share
        check_fits(replicas, shards, share, None, resources)
    for cpus, replicas in ((2, 2), (1, 1), (0, 1)):
        with pytest.raises(ValueError, match=r"none is left for the partitions"):
            fit_partition_cpus(replicas, 2, {"CPU": float(cpus)})


def test_a_replica_keeps_to_its_num_cpus(ray_cluster: str) -> None:
    """A replica's threads are the CPUs Ray gave it (whole, at least 1), not the machine's
    cores: read as the app's replicas read them (`use_replica_cpus`, in their constructors),
    in Ray actors given what a replica's `ray_actor_options` give (a Serve replica is one;
    under direct ingress a second app would find no port for its own)."""
    import ray

    from links_ray.serve.deployments import use_replica_cpus

    @ray.remote
    class Replica:
        def __init__(self) -> None:
            use_replica_cpus()

        def cpus(self) -> tuple[float | None, int]:
            from links_ray.engine.cpus import given_cpus, usable_cpus

            return given_cpus(), usable_cpus()

    for num_cpus, expected in ((0.5, (0.5, 1)), (1, (1.0, 1)), (0, (0.0, 1))):
        replica = Replica.options(num_cpus=num_cpus).remote()
        try:
            assert ray.get(replica.cpus.remote(), timeout=120) == expected
        finally:
            ray.kill(replica)


def _check_serve_config(config: dict[str, Any]) -> Any:
    from ray.serve.schema import ServeDeploySchema

    from links_ray.serve.app import app_builder

    schema = ServeDeploySchema.model_validate(config)
    (app,) = schema.applications
    assert app.name == "links" and app.route_prefix == "/"
    module, _, name = app.import_path.partition(":")
    assert getattr(importlib.import_module(module), name) is app_builder
    assert schema.logging_config.enable_access_log is False
    return schema


def test_serve_config_file() -> None:
    config = yaml.safe_load((REPO / "deploy/serve/serve_config.yaml").read_text())
    schema = _check_serve_config(config)
    assert schema.http_options.host == "127.0.0.1"
    assert schema.http_options.port == 8000


def test_rayservice_manifest() -> None:
    manifest = yaml.safe_load((REPO / "deploy/kuberay/rayservice.yaml").read_text())
    assert manifest["apiVersion"] == "ray.io/v1" and manifest["kind"] == "RayService"
    spec = manifest["spec"]
    schema = _check_serve_config(yaml.safe_load(spec["serveConfigV2"]))
    args = schema.applications[0].args
    assert args["root"] == "s3://links/dataset"
    # The full dataset, sharded (deploy/RUNBOOK.md, 6): args the app builder takes.
    from links_ray.serve.app import APP_ARGS, _arg

    assert set(args) <= set(APP_ARGS)
    given = {name: _arg(args, name) for name in args if name != "root"}
    assert given == {"replicas": 1, "shards": 32, "shard_cpus": 7.0, "shard_memory_gb": 8.0}
    cluster = spec["rayClusterConfig"]
    pods = [cluster["headGroupSpec"]] + cluster["workerGroupSpecs"]
    from links_ray.serve.deployments import SHUTDOWN_DRAIN_S

    for pod in pods:
        # Kubernetes kills a pod this long after SIGTERM: the replicas' drain, and the 10 s
        # `links serve` may take to stop once idle
        # (test_links_serve_finishes_a_request_under_way_at_sigterm).
        assert pod["template"]["spec"]["terminationGracePeriodSeconds"] == SHUTDOWN_DRAIN_S + EXIT_S
        (container,) = pod["template"]["spec"]["containers"]
        assert container["image"] == "links-ray:latest"
        env = {item["name"]: item for item in container["env"]}
        for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
            ref = env[key]["valueFrom"]["secretKeyRef"]
            assert ref == {"name": "links-s3-credentials", "key": key}
            assert "value" not in env[key]
