"""The NetworkPolicies of deploy/public/ against the pods they guard, without a cluster.

A NetworkPolicy selects every pod of each RayService behind an Ingress, and no pod of anything
else; it admits the ingress controller on the Serve port alone, the KubeRay operator on the
dashboard's alone, and every port from the RayService's own pods only; another selects the quota
service's pods and admits the ingress controller on its port alone. No rule admits every
source, an address block, or another pod.

Each check returns the problems it finds, and `test_a_planted_mistake_is_found` shows each one
finding a mistake planted in a copy (tests/support/manifests.py holds the parsed manifests and
the helpers the test_deploy_*.py files share).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import yaml

from tests.support.manifests import (
    MANIFESTS,
    QUOTA,
    Check,
    Manifests,
    Plant,
    edit,
    exposed_services,
    named,
    objects,
    planted_copy,
    pod_templates,
    selects,
)

#: The ingress controller's pods and namespace, as the NetworkPolicies name them.
CONTROLLER_NAMESPACE = "ingress-nginx"
CONTROLLER_LABELS = {
    "app.kubernetes.io/name": "ingress-nginx",
    "app.kubernetes.io/component": "controller",
}
#: The KubeRay operator's, and the one port of a Ray head it needs: the dashboard's.
OPERATOR_NAMESPACE, OPERATOR_LABELS = (
    "kuberay-system",
    {"app.kubernetes.io/name": "kuberay-operator"},
)
DASHBOARD_PORT = 8265


def all_pod_labels(manifests: Manifests) -> list[tuple[str, dict]]:
    """(where, labels) of every pod template under deploy/: any mapping with metadata and a
    spec holding containers, however deep in its object."""
    found = []

    def walk(where: str, value: Any) -> None:
        if isinstance(value, dict):
            if isinstance(value.get("spec"), dict) and "containers" in value["spec"]:
                found.append((where, value.get("metadata", {}).get("labels", {})))
            for item in value.values():
                walk(where, item)
        elif isinstance(value, list):
            for item in value:
                walk(where, item)

    for where, documents in manifests.items():
        for doc in documents:
            if isinstance(doc, dict) and "kind" in doc:
                walk(f"{where}: {doc['metadata']['name']}", doc)
    return found


def peer_kind(peer: dict, own: dict) -> str:
    """What a NetworkPolicy peer is: "own" (pods of the policy's own selector, in its
    namespace), "controller" or "operator" (their pods in their namespace), else "other"."""
    if set(peer) == {"podSelector"} and peer["podSelector"] == own:
        return "own"
    namespace = peer.get("namespaceSelector", {}).get("matchLabels", {})
    pods = peer.get("podSelector", {}).get("matchLabels", {})
    name = namespace.get("kubernetes.io/metadata.name")
    if set(peer) == {"namespaceSelector", "podSelector"}:
        if name == CONTROLLER_NAMESPACE and CONTROLLER_LABELS.items() <= pods.items():
            return "controller"
        if name == OPERATOR_NAMESPACE and OPERATOR_LABELS.items() <= pods.items():
            return "operator"
    return "other"


def rule_ports(rule: dict) -> set[int] | None:
    """The TCP ports a NetworkPolicy rule admits, None for every port."""
    if not rule.get("ports"):
        return None
    return {p["port"] for p in rule["ports"] if p.get("protocol", "TCP") == "TCP"}


# -- the checks -----------------------------------------------------------------------------


def network_problems(manifests: Manifests) -> list[str]:
    """A NetworkPolicy selects every pod of each RayService behind an Ingress, and no pod of
    anything else; it admits the ingress controller on the Serve port alone, the KubeRay
    operator on the dashboard's alone, and every port from the RayService's own pods only;
    another selects the quota service's pods and admits the ingress controller on its port
    alone. No rule admits every source, an address block, or another pod."""
    problems = []
    # (where, its pod templates, the port the controller may reach, the operator's, whether
    # its own pods may reach each other on every port: Ray's do)
    guarded: list[tuple[str, list[dict], int, set[int], bool]] = []
    exposed = exposed_services(manifests)
    for where, service in objects(manifests, "RayService"):
        if service["metadata"]["name"] in exposed:
            config = yaml.safe_load(service["spec"]["serveConfigV2"])
            templates = [t for _, t in pod_templates(service["spec"]["rayClusterConfig"])]
            port = config["http_options"]["port"]
            guarded.append((where, templates, port, {DASHBOARD_PORT}, True))
    quota = named(manifests, "Deployment", QUOTA)
    if quota is not None:
        template = quota[1]["spec"]["template"]
        (container,) = template["spec"]["containers"]
        port = container["ports"][0]["containerPort"]
        guarded.append((quota[0], [template], port, set(), False))
    for where, templates, port, operator_ports, ray in guarded:
        problems += guarded_problems(manifests, where, templates, port, operator_ports, ray)
    return problems


def guarded_problems(
    manifests: Manifests,
    where: str,
    templates: list[dict],
    port: int,
    operator_ports: set[int],
    ray: bool,
) -> list[str]:
    """`network_problems` for the pods of `templates`: the NetworkPolicies that select them
    all select no other pod, and admit the controller on `port`, the operator on
    `operator_ports` and, if `ray`, these pods on every port; nothing else."""
    problems = []
    labels = [t["metadata"].get("labels", {}) for t in templates]
    mine = [
        (pw, policy)
        for pw, policy in objects(manifests, "NetworkPolicy")
        if "Ingress" in policy["spec"].get("policyTypes", ["Ingress"])
        and all(selects(policy["spec"]["podSelector"], each) for each in labels)
    ]
    if not mine:
        return [f"{where}: no NetworkPolicy selects all of its pods"]
    controller_ports: set[int] = set()
    for pw, policy in mine:
        own = policy["spec"]["podSelector"]
        for other_where, other in all_pod_labels(manifests):
            if selects(own, other) and other not in labels:
                problems.append(f"{pw}: its selector also takes the pods of {other_where}")
        for rule in policy["spec"].get("ingress", []):
            ports = rule_ports(rule)
            said = "every port" if ports is None else sorted(ports)
            for peer in rule.get("from") or [{}]:
                kind = peer_kind(peer, own) if peer else "every source"
                if kind == "controller" and ports is not None and ports <= {port}:
                    controller_ports |= ports
                elif kind == "operator" and ports is not None and ports <= operator_ports:
                    continue
                elif kind == "own" and ray:
                    continue
                else:
                    problems.append(f"{pw}: admits {kind} {peer or ''} on {said}".rstrip())
    if port not in controller_ports:
        problems.append(f"{where}: no policy admits the ingress controller on port {port}")
    return problems


# -- the tests ------------------------------------------------------------------------------


def test_network_policies_guard_the_serve_and_ray_ports() -> None:
    assert objects(MANIFESTS, "NetworkPolicy")
    assert network_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


POLICIES = "public/networkpolicy.yaml"


def policy_rule(index: int, change_rule: Callable[[dict], None]) -> Callable[[dict], None]:
    def change(policy: dict) -> None:
        change_rule(policy["spec"]["ingress"][index])

    return change


#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Check, Plant, str]] = [
    (
        network_problems,
        lambda m: edit(m, POLICIES, "links-public-ray", policy_rule(1, lambda r: r.pop("ports"))),
        "admits controller",
    ),
    (
        network_problems,
        lambda m: edit(m, POLICIES, "links-public-ray", policy_rule(0, lambda r: r.pop("from"))),
        "admits every source",
    ),
    (
        network_problems,
        lambda m: edit(
            m,
            POLICIES,
            "links-public-ray",
            lambda p: p["spec"].update(
                podSelector={"matchLabels": {"app.kubernetes.io/name": "links-ray"}}
            ),
        ),
        "also takes the pods of deploy/public/rayjob-demo.yaml",
    ),
    (
        network_problems,
        lambda m: edit(
            m,
            POLICIES,
            "links-quota",
            policy_rule(0, lambda r: r["from"].append({"podSelector": {}})),
        ),
        "admits other",
    ),
    (
        network_problems,
        lambda m: m[f"deploy/{POLICIES}"].pop(0),
        "no NetworkPolicy selects all of its pods",
    ),
]


@pytest.mark.parametrize(
    ("check", "plant", "phrase"), PLANTED, ids=[phrase for _, _, phrase in PLANTED]
)
def test_a_planted_mistake_is_found(check: Check, plant: Plant, phrase: str) -> None:
    found = check(planted_copy(plant))
    assert any(phrase in problem for problem in found), found
