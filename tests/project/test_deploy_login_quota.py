"""The login and the quota service in front of every route that costs, without a cluster.

Every Ingress that routes a route of the app beyond OPEN_ROUTES asks for one login (one Secret,
one realm) and then the quota service (deploy/public/quota.yaml, its `auth-url`), which gives
every such route a per-user quota and a global cap, runs as one replica, and, run here over HTTP
as its ConfigMap ships it, enforces them; the Ingress of /api/synthesize limits each client more
tightly than every other.

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from tests.support.manifests import (
    INGRESS,
    MANIFESTS,
    OPEN_ROUTES,
    QUOTA,
    SYNTHESIZE,
    Check,
    Manifests,
    Plant,
    add_path,
    annotation,
    app_routes,
    edit,
    named,
    objects,
    per_minute,
    planted_copy,
    routes_of,
    selects,
    set_annotation,
)

# -- the checks -----------------------------------------------------------------------------


def auth_problems(manifests: Manifests) -> list[str]:
    """Every Ingress that routes a route of the app beyond OPEN_ROUTES asks for a login (basic
    auth against a Secret: one Secret and one realm for all, so a browser asks once) and then
    the quota service (`auth-url`); the one that routes /api/synthesize limits each client more
    tightly than every other Ingress of the host, in rate and in connections."""
    problems = []
    routes = app_routes()
    ingresses = objects(manifests, "Ingress")
    logins = set()
    for where, ingress in ingresses:
        costly = sorted(routes_of(ingress, routes) - OPEN_ROUTES)
        if not costly:
            continue
        if annotation(ingress, "auth-type") == "basic" and annotation(ingress, "auth-secret"):
            logins.add((annotation(ingress, "auth-secret"), annotation(ingress, "auth-realm")))
        else:
            problems.append(f"{where}: routes {costly} without a login")
        if annotation(ingress, "auth-url") is None:
            problems.append(f"{where}: routes {costly} without {QUOTA}'s check (auth-url)")
    if len(logins) > 1:
        problems.append(f"logins {sorted(logins, key=str)}: a browser would ask for each")
    for where, ingress in ingresses:
        if SYNTHESIZE not in routes_of(ingress, routes):
            continue
        for other_where, other in ingresses:
            if other is ingress or SYNTHESIZE in routes_of(other, routes):
                continue
            mine, theirs = per_minute(ingress), per_minute(other)
            if mine is not None and theirs is not None and mine >= theirs:
                problems.append(
                    f"{where}: {mine:g} a minute, no tighter than {other_where}'s {theirs:g}"
                )
            mine_c = annotation(ingress, "limit-connections")
            theirs_c = annotation(other, "limit-connections")
            if mine_c and theirs_c and int(mine_c) > int(theirs_c):
                problems.append(
                    f"{where}: {mine_c} connections, more than {other_where}'s {theirs_c}"
                )
    return problems


def quota_limits(manifests: Manifests) -> dict[str, dict[str, list[float]]]:
    """The quota service's quotas.json: route to its per-user and all-users rate and burst."""
    found = named(manifests, "ConfigMap", QUOTA)
    return json.loads(found[1]["data"]["quotas.json"]) if found else {}


def quota_problems(manifests: Manifests) -> list[str]:
    """The quota service gives every route of the app beyond OPEN_ROUTES a per-user quota and
    a global cap (positive requests a minute and bursts, each user's within all users'), and no
    route the app lacks; it runs as one replica (its counts are the global ones); every
    Ingress's `auth-url` reaches its Service, whose port reaches its container."""
    problems = []
    limits = quota_limits(manifests)
    routes = app_routes()
    for route in sorted(routes - OPEN_ROUTES - set(limits)):
        problems.append(f"{QUOTA}: {route} has no quota")
    for route, limit in sorted(limits.items()):
        if route not in routes:
            problems.append(f"{QUOTA}: {route} is no route of the app")
        if set(limit) != {"user", "all"} or any(len(limit[k]) != 2 for k in limit):
            problems.append(f"{QUOTA}: {route} needs [a minute, burst] for user and all")
            continue
        if min(*limit["user"], *limit["all"]) <= 0:
            problems.append(f"{QUOTA}: {route} has a rate or burst that lets nothing through")
        if any(u > a for u, a in zip(limit["user"], limit["all"], strict=True)):
            problems.append(f"{QUOTA}: {route} lets a user more than all users' {limit['all']}")
    deployment, service = named(manifests, "Deployment", QUOTA), named(manifests, "Service", QUOTA)
    if deployment is None or service is None:
        return [*problems, f"no Deployment and Service {QUOTA} under deploy/"]
    spec = deployment[1]["spec"]
    if spec.get("replicas", 1) != 1:
        problems.append(f"{deployment[0]}: {spec['replicas']} replicas would each count apart")
    (container,) = spec["template"]["spec"]["containers"]
    ports = {p.get("name"): p["containerPort"] for p in container["ports"]}
    labels = spec["template"]["metadata"]["labels"]
    if not selects(service[1]["spec"]["selector"], labels):
        problems.append(f"{service[0]}: its selector misses the {QUOTA} pods")
    service_ports = {p["port"]: p.get("targetPort", p["port"]) for p in service[1]["spec"]["ports"]}
    for where, ingress in objects(manifests, "Ingress"):
        url = annotation(ingress, "auth-url")
        if url is None:
            continue
        parts = urlsplit(url)
        host = parts.hostname or ""
        if host.split(".")[0] != QUOTA or parts.port not in service_ports:
            problems.append(f"{where}: auth-url {url} is not {QUOTA}'s Service and port")
            continue
        target = service_ports[parts.port]
        if target not in ports and target not in ports.values():
            problems.append(f"{service[0]}: port {parts.port} leads to no port of the container")
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_synthesis_needs_a_login_and_has_the_tightest_limits() -> None:
    routes = app_routes()
    assert SYNTHESIZE in routes
    assert any(SYNTHESIZE in routes_of(i, routes) for _, i in objects(MANIFESTS, "Ingress"))
    assert auth_problems(MANIFESTS) == []


def test_every_costly_route_needs_the_login_and_passes_a_quota() -> None:
    routes = app_routes()
    assert routes - OPEN_ROUTES >= {SYNTHESIZE, "/api/retrieve", "/api/kit", "/api/curve"}
    assert auth_problems(MANIFESTS) == []
    assert quota_problems(MANIFESTS) == []
    # The open routes are only those: each is routed, and by an Ingress without a login.
    for _, ingress in objects(MANIFESTS, "Ingress"):
        if annotation(ingress, "auth-type") is None:
            assert routes_of(ingress, routes) <= OPEN_ROUTES


def quota_check(
    port: int, route: str, user: str | None, headers: dict[str, str] | None = None
) -> int:
    """The status the quota service answers for `user`'s request to `route`, asked as
    ingress-nginx asks (the request's headers, its URL in X-Original-URL, no body)."""
    import base64
    import http.client

    sent = {"X-Original-URL": f"https://links.example.org{route}?x=1", **(headers or {})}
    if user is not None:
        sent["Authorization"] = "Basic " + base64.b64encode(f"{user}:pw".encode()).decode()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", "/check", headers=sent)
        response = conn.getresponse()
        response.read()
        return response.status
    finally:
        conn.close()


def test_the_quota_service_counts_each_user_and_all_users(tmp_path: Path) -> None:
    """quota.py as the ConfigMap ships it, over HTTP: each user gets their burst, then 403
    while another user still passes; past the route's cap for all users, everyone gets 403;
    a route with no quota and a request with no user are refused. The rates are one a minute,
    so no token comes back while the test runs."""
    import socket
    import subprocess
    import sys
    import time

    found = named(MANIFESTS, "ConfigMap", QUOTA)
    assert found is not None
    config_map = found[1]
    script = tmp_path / "quota.py"
    script.write_text(config_map["data"]["quota.py"])
    limits = {
        "/api/synthesize": {"user": [1, 2], "all": [1, 5]},
        "/api/kit": {"user": [1, 1], "all": [1, 9]},
    }
    (tmp_path / "quotas.json").write_text(json.dumps(limits))
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "quotas.json"), str(port)],
        stderr=subprocess.PIPE,
    )
    try:
        for _ in range(100):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
                break
            time.sleep(0.1)
        synthesize = "/api/synthesize"
        assert [quota_check(port, synthesize, "alice") for _ in range(3)] == [204, 204, 403]
        assert quota_check(port, "/api/kit", "alice") == 204  # each route its own quota
        assert quota_check(port, "/api/kit", "alice") == 403
        # The global cap, 5: alice's 2, then bob's 2, then carol's first; dave gets none.
        assert [quota_check(port, synthesize, "bob") for _ in range(3)] == [204, 204, 403]
        assert quota_check(port, synthesize, "carol") == 204
        assert quota_check(port, synthesize, "dave") == 403
        assert quota_check(port, "/api/nope", "erin") == 403  # no quota: no work
        assert quota_check(port, synthesize, None) == 401
        assert quota_check(port, synthesize, None, {"Authorization": "Basic %%%"}) == 401
    finally:
        server.terminate()
        _, errors = server.communicate(timeout=10)
    assert b"Traceback" not in errors, errors.decode()


# -- each check finds a planted mistake -----------------------------------------------------


QUOTAS = "public/quota.yaml"


def set_quota(route: str, limit: dict | None) -> Callable[[dict], None]:
    def change(config_map: dict) -> None:
        limits = json.loads(config_map["data"]["quotas.json"])
        if limit is None:
            limits.pop(route)
        else:
            limits[route] = limit
        config_map["data"]["quotas.json"] = json.dumps(limits)

    return change


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public-synthesize", set_annotation("auth-type", None)),
        "without a login",
    ),
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public", add_path("/api", "Prefix")),
        "without a login",
    ),
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public-synthesize", set_annotation("limit-rpm", "6000")),
        "no tighter than",
    ),
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public", add_path("/api/curve", "Exact")),
        "without a login",
    ),
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public-kit", set_annotation("auth-url", None)),
        "without links-quota's check",
    ),
    (
        auth_problems,
        lambda m: edit(m, INGRESS, "links-public-kit", set_annotation("auth-realm", "kits")),
        "a browser would ask for each",
    ),
    (
        quota_problems,
        lambda m: edit(m, QUOTAS, QUOTA, set_quota("/api/retrieve", None)),
        "/api/retrieve has no quota",
    ),
    (
        quota_problems,
        lambda m: edit(m, QUOTAS, QUOTA, set_quota(SYNTHESIZE, {"user": [60, 2], "all": [20, 4]})),
        "lets a user more than all users'",
    ),
    (
        quota_problems,
        lambda m: named(m, "Deployment", QUOTA)[1]["spec"].update(replicas=2),
        "would each count apart",
    ),
    (
        quota_problems,
        lambda m: edit(
            m,
            INGRESS,
            "links-public-edit",
            set_annotation("auth-url", "http://links-quota.links.svc.cluster.local:9090/check"),
        ),
        "is not links-quota's Service and port",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
