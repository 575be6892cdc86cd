"""The Ingresses of deploy/ against the Serve app they route, without a cluster.

Every Ingress routes only routes the app has, each route through exactly one Ingress of a host,
to a RayService's Serve Service and port, for a named host under TLS that the RayService's
`allowed_hosts` names; it limits each client's rate and connections, passes bodies up to the
app's limit and no larger, waits as long as its routes may take, keeps access logs on and uses
no snippets. The login and the quotas in front of the costly routes: test_deploy_login_quota.py.

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

import re

import pytest
import yaml

from links_ray.engine.synthesis.options import MAX_SYNTHESIS_SECONDS
from links_ray.serve.http.limits import MAX_BODY_BYTES, PARTITION_TIMEOUT_S
from tests.support.manifests import (
    INGRESS,
    MANIFESTS,
    PUBLIC,
    SYNTHESIZE,
    Check,
    Manifests,
    Plant,
    add_path,
    annotation,
    app_routes,
    backend_service,
    edit,
    edit_serve,
    ingress_paths,
    matches,
    objects,
    per_minute,
    planted_copy,
    routes_of,
    set_annotation,
    the_app,
)


def nginx_size(text: str) -> int | None:
    """Bytes of an nginx size ("2m": 2 MiB; nginx's k, m and g are powers of 1024)."""
    found = re.fullmatch(r"(\d+)([kKmMgG]?)", text.strip())
    if found is None:
        return None
    return int(found[1]) * 1024 ** " kmg".index(found[2].lower() or " ")


# -- the checks -----------------------------------------------------------------------------


def ingress_problems(manifests: Manifests) -> list[str]:
    """Each Ingress routes only routes of the app, to a RayService's Serve Service and port,
    for a named host under TLS that the RayService allows; limits each client's rate and
    connections; passes bodies up to the app's limit and no larger; waits as long as its
    routes may take; keeps access logs on and uses no snippets. Every route of the app is
    routed by exactly one Ingress of a host."""
    problems = []
    routes = app_routes()
    services = {}
    for _, service in objects(manifests, "RayService"):
        config = yaml.safe_load(service["spec"]["serveConfigV2"])
        services[service["metadata"]["name"] + "-serve-svc"] = config
    routed: dict[tuple[str | None, str], list[str]] = {}
    for where, ingress in objects(manifests, "Ingress"):
        tls_hosts = {h for tls in ingress["spec"].get("tls", []) for h in tls.get("hosts", [])}
        for host, entry in ingress_paths(ingress):
            path, path_type = entry["path"], entry.get("pathType", "Prefix")
            hits = [route for route in routes if matches(path, path_type, route)]
            if not hits:
                problems.append(f"{where}: {path} ({path_type}) is no route of the app")
            for route in hits:
                routed.setdefault((host, route), []).append(where)
        for rule in ingress["spec"].get("rules", []):
            if rule.get("host") is None:
                problems.append(f"{where}: a rule without a host answers any Host")
            elif rule["host"] not in tls_hosts:
                problems.append(f"{where}: {rule['host']} is not under TLS")
        if annotation(ingress, "ssl-redirect") == "false":
            problems.append(f"{where}: plain HTTP is not redirected to HTTPS")
        for name, port in backend_service(ingress):
            config = services.get(name)
            if config is None:
                problems.append(f"{where}: {name} is no RayService's Serve Service")
                continue
            if port != config["http_options"]["port"]:
                problems.append(
                    f"{where}: port {port}, the proxies listen on {config['http_options']['port']}"
                )
            allowed = the_app(config).get("args", {}).get("allowed_hosts", ["*"])
            hosts = {host for host, _ in ingress_paths(ingress)}
            if "*" in allowed or not hosts <= set(allowed):
                problems.append(
                    f"{where}: allowed_hosts {allowed} of {name} must name {sorted(hosts)}"
                )
        if per_minute(ingress) is None:
            problems.append(f"{where}: no limit-rps or limit-rpm")
        for name in ("limit-connections", "limit-burst-multiplier"):
            if annotation(ingress, name) is None:
                problems.append(f"{where}: no {name}")
        size = annotation(ingress, "proxy-body-size")
        if size is None or nginx_size(size) != MAX_BODY_BYTES:
            problems.append(
                f"{where}: proxy-body-size {size!r} is not the app's {MAX_BODY_BYTES} bytes"
            )
        served = routes_of(ingress, routes)
        longest = 0.0
        if served & {"/api/retrieve", SYNTHESIZE}:  # a partitioned gateway waits for its partitions
            longest = PARTITION_TIMEOUT_S
        if SYNTHESIZE in served:  # its wait for another, its budget, its retrieval
            longest = 2 * MAX_SYNTHESIS_SECONDS + PARTITION_TIMEOUT_S
        for name in ("proxy-connect-timeout", "proxy-read-timeout"):
            if annotation(ingress, name) is None:
                problems.append(f"{where}: no {name}")
        read = float(annotation(ingress, "proxy-read-timeout") or 60)  # nginx's default
        if read < longest:
            problems.append(
                f"{where}: proxy-read-timeout {read:g} s, its routes may take {longest:g}"
            )
        if annotation(ingress, "enable-access-log") == "false":
            problems.append(f"{where}: access logs turned off")
        for name in ingress["metadata"].get("annotations", {}):
            if name.endswith("-snippet"):
                problems.append(f"{where}: {name}: a snippet can log or pass what nothing checks")
    hosts = {host for host, _ in routed}
    for host in sorted(hosts, key=str):
        for route in routes:
            by = routed.get((host, route), [])
            if len(by) != 1:
                problems.append(f"{host}: {route} is routed by {len(by)} paths ({by}), not one")
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_ingresses_route_the_app_with_tls_limits_and_the_body_limit() -> None:
    assert len(objects(MANIFESTS, "Ingress")) >= 2
    assert ingress_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public", add_path("/api", "Prefix")),
        "routed by 2 paths",
    ),
    (
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public", add_path("/api/nope", "Exact")),
        "no route of the app",
    ),
    (
        ingress_problems,
        lambda m: edit(
            m, INGRESS, "links-public-retrieve", set_annotation("proxy-body-size", "1m")
        ),
        "proxy-body-size",
    ),
    (
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public-retrieve", set_annotation("limit-rps", None)),
        "no limit-rps or limit-rpm",
    ),
    (
        ingress_problems,
        lambda m: edit(
            m, INGRESS, "links-public-synthesize", set_annotation("proxy-read-timeout", "60")
        ),
        "proxy-read-timeout 60 s",
    ),
    (
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public", set_annotation("enable-access-log", "false")),
        "access logs turned off",
    ),
    (
        ingress_problems,
        lambda m: edit_serve(
            m, PUBLIC, "links-public", lambda app: app["args"].update(allowed_hosts=["*"])
        ),
        "allowed_hosts",
    ),
    (
        ingress_problems,
        lambda m: edit(
            m,
            INGRESS,
            "links-public-retrieve",
            lambda i: i["spec"]["rules"][0]["http"]["paths"][0]["backend"]["service"].update(
                name="links-serve-svc"
            ),
        ),
        "no RayService's Serve Service",
    ),
    (
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public", lambda i: i["spec"].pop("tls")),
        "not under TLS",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
