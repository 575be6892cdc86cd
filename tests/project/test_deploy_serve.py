"""deploy/'s YAML files and its Ray Serve configs against the code they run, without a cluster.

Every YAML file parses into Kubernetes objects or Serve configs; every Serve config (the files of
deploy/serve/ and each RayService's serveConfigV2) builds the links app with args it takes, and
its deployment overrides keep the replicas' environment; each RayService's workers offer Ray the
CPUs its replicas reserve, the head none, and give the replicas time to drain.
(tests/serve/test_serve_config.py checks the private Serve config's and RayService's own
values.)

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import pytest
import yaml

from links_ray.serve.app import APP_ARGS, PARTITION_CPUS, _arg
from links_ray.serve.deployments import REPLICA_ENV, SHUTDOWN_DRAIN_S, LinksApi
from links_ray.serve.http.middleware import as_host_names
from tests.support.manifests import (
    MANIFESTS,
    PUBLIC,
    Check,
    Manifests,
    Plant,
    edit_serve,
    objects,
    planted_copy,
    pod_templates,
    serve_configs,
    the_app,
)

APP_BUILDER = "links_ray.serve.app:app_builder"
#: Ray's logical CPUs of a RayService's replicas: the gateway's unless the config says otherwise.
GATEWAY_CPUS = float(LinksApi.ray_actor_options["num_cpus"])


def cpus(quantity: str | float | int) -> float:
    """A Kubernetes CPU quantity ("16", "500m") in CPUs."""
    text = str(quantity)
    return float(text[:-1]) / 1000 if text.endswith("m") else float(text)


# -- the checks -----------------------------------------------------------------------------


def serve_config_problems(manifests: Manifests) -> list[str]:
    """Each Serve config validates, builds the links app, and gives it only args it takes,
    of its types; its deployment overrides name deployments the app has and keep the
    replicas' environment (an override's ray_actor_options replace the code's whole)."""
    from pydantic import ValidationError
    from ray.serve.schema import ServeDeploySchema

    problems = []
    for where, config in serve_configs(manifests):
        try:
            ServeDeploySchema.model_validate(config)
        except ValidationError as exc:
            problems.append(f"{where}: not a Serve config: {exc.errors()[0]['msg']}")
            continue
        app = the_app(config)
        if app["import_path"] != APP_BUILDER:
            problems.append(f"{where}: imports {app['import_path']}, not {APP_BUILDER}")
        args = app.get("args", {})
        if not str(args.get("root", "")).strip():
            problems.append(f"{where}: no args.root")
        for name in sorted(set(args) - set(APP_ARGS)):
            problems.append(f"{where}: args.{name} is not an arg of the app ({sorted(APP_ARGS)})")
        for name in sorted(set(args) & set(APP_ARGS) - {"root", "allowed_hosts"}):
            try:
                _arg(args, name)
            except ValueError as exc:
                problems.append(f"{where}: {exc}")
        if "allowed_hosts" in args:
            try:
                as_host_names(args["allowed_hosts"])
            except ValueError as exc:
                problems.append(f"{where}: args.allowed_hosts: {exc}")
        deployments = {LinksApi.name}
        with contextlib.suppress(KeyError, ValueError):  # no shards, or reported above
            shards = _arg(args, "shards")
            deployments |= {f"IndexPartition-{part}-of-{shards}" for part in range(shards)}
        for override in app.get("deployments", []):
            if override["name"] not in deployments:
                problems.append(f"{where}: the app has no deployment {override['name']!r}")
            options = override.get("ray_actor_options")
            if options is not None:
                env = options.get("runtime_env", {}).get("env_vars", {})
                if any(env.get(name) != value for name, value in REPLICA_ENV.items()):
                    problems.append(
                        f"{where}: {override['name']}'s ray_actor_options drop the replicas' "
                        f"env_vars {REPLICA_ENV} (they replace the code's whole)"
                    )
    return problems


def fit_problems(manifests: Manifests) -> list[str]:
    """Each RayService's workers offer Ray the CPUs its replicas reserve, in all and on one
    node for the largest replica (the head takes none), and give them time to drain."""
    problems = []
    for where, service in objects(manifests, "RayService"):
        app = the_app(yaml.safe_load(service["spec"]["serveConfigV2"]))
        args = app.get("args", {})
        replicas = int(args.get("replicas", 1))
        overrides = {o["name"]: o for o in app.get("deployments", [])}
        gateway = overrides.get(LinksApi.name, {})
        gateway_cpus = float(gateway.get("ray_actor_options", {}).get("num_cpus", GATEWAY_CPUS))
        needed = gateway.get("num_replicas", replicas) * gateway_cpus
        largest = gateway_cpus
        if args.get("shards"):
            shard_cpus = float(args.get("shard_cpus", PARTITION_CPUS))
            needed += int(args["shards"]) * replicas * shard_cpus
            largest = max(largest, shard_cpus)
        cluster = service["spec"]["rayClusterConfig"]
        nodes = []
        for group in cluster.get("workerGroupSpecs", []):
            (container,) = group["template"]["spec"]["containers"]
            offered = group.get("rayStartParams", {}).get("num-cpus")
            node = cpus(offered if offered is not None else container["resources"]["limits"]["cpu"])
            nodes += [node] * int(group["replicas"])
        if needed > sum(nodes) + 1e-9:
            problems.append(
                f"{where}: the replicas reserve {needed:g} CPUs, workers offer {sum(nodes):g}"
            )
        if largest > max(nodes, default=0.0) + 1e-9:
            problems.append(f"{where}: a replica of {largest:g} CPUs fits on no worker")
        head = cluster["headGroupSpec"]
        if str(head.get("rayStartParams", {}).get("num-cpus")) != "0":
            problems.append(f"{where}: the head offers CPUs: replicas could land beside the GCS")
        for group, template in pod_templates(cluster):
            grace = template["spec"].get("terminationGracePeriodSeconds", 30)
            if grace < SHUTDOWN_DRAIN_S:
                problems.append(
                    f"{where}: {group} pods get {grace} s, the drain takes {SHUTDOWN_DRAIN_S:g}"
                )
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_every_yaml_file_parses_into_kubernetes_objects_or_serve_configs() -> None:
    assert len(MANIFESTS) >= 10
    for where, documents in MANIFESTS.items():
        assert documents, f"{where} is empty"
        for doc in documents:
            assert isinstance(doc, dict), where
            if where.startswith("deploy/serve/"):
                assert "applications" in doc, where
            else:
                assert doc.get("apiVersion") and doc.get("kind"), where
                assert doc.get("metadata", {}).get("name"), where
    kinds = {doc["kind"] for documents in MANIFESTS.values() for doc in documents if "kind" in doc}
    assert {"RayService", "RayJob", "Ingress", "ConfigMap", "Secret"} <= kinds


def test_serve_configs_build_the_links_app_with_args_it_takes() -> None:
    assert len(serve_configs(MANIFESTS)) >= 3  # the file and both RayServices
    assert serve_config_problems(MANIFESTS) == []


def test_rayservices_fit_their_workers() -> None:
    assert fit_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


def gateway_override(change_options: Callable[[dict], None]) -> Callable[[dict], None]:
    def change(app: dict) -> None:
        change_options(app["deployments"][0]["ray_actor_options"])

    return change


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        serve_config_problems,
        lambda m: edit_serve(m, PUBLIC, "links-public", lambda app: app["args"].update(replica=2)),
        "args.replica is not an arg",
    ),
    (
        serve_config_problems,
        lambda m: edit_serve(
            m, PUBLIC, "links-public", gateway_override(lambda options: options.pop("runtime_env"))
        ),
        "drop the replicas' env_vars",
    ),
    (
        serve_config_problems,
        lambda m: edit_serve(
            m, PUBLIC, "links-public", lambda app: app["deployments"][0].update(name="Front")
        ),
        "no deployment 'Front'",
    ),
    (
        fit_problems,
        lambda m: edit_serve(
            m, PUBLIC, "links-public", gateway_override(lambda options: options.update(num_cpus=3))
        ),
        "fits on no worker",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
