"""The manifests under deploy/, parsed, and the helpers tests/project/test_deploy_*.py share.

MANIFESTS holds every YAML file under deploy/, loaded once for all the files that check it:
test_deploy_serve.py (every file parses; the Serve configs; the RayServices' CPUs),
test_deploy_ingress.py (the Ingresses), test_deploy_login_quota.py (the login and the quota
service), test_deploy_network.py (the NetworkPolicies), test_deploy_s3_keys.py (the S3 keys and
their MinIO policies) and test_deploy_jobs.py (the RayJobs' `links` commands). The helpers find
its objects, the Serve app's routes and what an Ingress routes where; `planted_copy`, with
`edit`, `edit_serve`, `set_annotation` and `add_path`, plants a mistake in a copy of it for a
check to find.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"

#: Documents of each YAML file under deploy/, by path from the repository root.
Manifests = dict[str, list[Any]]
#: A check: the problems it finds in the manifests.
Check = Callable[[Manifests], list[str]]
#: A mistake planted in the manifests.
Plant = Callable[[Manifests], None]

SYNTHESIZE = "/api/synthesize"
NGINX = "nginx.ingress.kubernetes.io/"
#: The routes anyone may ask without a login: the studio's page and files, and what computes
#: nothing (health, the request limits, the OpenAPI document). Every other route costs.
OPEN_ROUTES = {"/", "/studio/{name}", "/api/health", "/api/limits", "/openapi.json"}
#: The quota service's name (its ConfigMap, Deployment, Service and pod label).
QUOTA = "links-quota"


def load_manifests() -> Manifests:
    """Every YAML file under deploy/, each as its list of documents (empty ones dropped)."""
    found = {}
    for path in sorted([*DEPLOY.rglob("*.yaml"), *DEPLOY.rglob("*.yml")]):
        documents = list(yaml.safe_load_all(path.read_text()))
        found[str(path.relative_to(REPO))] = [doc for doc in documents if doc is not None]
    return found


MANIFESTS = load_manifests()


def objects(manifests: Manifests, kind: str) -> list[tuple[str, dict]]:
    """(`file: name`, object) of every Kubernetes object of `kind`."""
    return [
        (f"{where}: {doc['metadata']['name']}", doc)
        for where, documents in manifests.items()
        for doc in documents
        if isinstance(doc, dict) and doc.get("kind") == kind
    ]


def named(manifests: Manifests, kind: str, name: str) -> tuple[str, dict] | None:
    """(where, object) of the object `name` of `kind`, None if there is none."""
    found = [(w, o) for w, o in objects(manifests, kind) if o["metadata"]["name"] == name]
    return found[0] if found else None


def serve_configs(manifests: Manifests) -> list[tuple[str, dict]]:
    """(where, config) of every Ray Serve config: the files of deploy/serve/ and each
    RayService's serveConfigV2."""
    configs = [
        (where, doc)
        for where, documents in manifests.items()
        if where.startswith("deploy/serve/")
        for doc in documents
    ]
    for where, service in objects(manifests, "RayService"):
        configs.append((where, yaml.safe_load(service["spec"]["serveConfigV2"])))
    return configs


def the_app(config: dict) -> dict:
    """The links application of a Serve config."""
    (app,) = config["applications"]
    return app


def app_routes() -> set[str]:
    """The paths of the Serve app's routes (`{name}` for a parameter), from its OpenAPI
    document (`api.routes` itself holds Serve's wrapper of the class's routes once
    `serve.ingress` has run), and the document's own path."""
    from links_ray.serve.http.asgi import api, api_openapi

    return {*api_openapi()["paths"], api.openapi_url}


def route_pattern(route: str) -> re.Pattern[str]:
    """A route's path as a pattern: each `{name}` one path element."""
    pieces = re.split(r"\{[^/}]+\}", route)
    return re.compile("[^/]+".join(map(re.escape, pieces)))


def matches(path: str, path_type: str, route: str) -> bool:
    """Whether an Ingress path of `path_type` sends requests for `route` to the backend."""
    if path_type == "Exact":
        return route_pattern(route).fullmatch(path) is not None
    prefix = path.rstrip("/")
    # Kubernetes' Prefix matches whole path elements: /studio matches /studio/x, not /studios.
    return prefix == "" or route == prefix or route.startswith(prefix + "/")


def ingress_paths(ingress: dict) -> Iterator[tuple[str | None, dict]]:
    """(host, path entry) of every path of an Ingress."""
    for rule in ingress["spec"].get("rules", []):
        for entry in rule.get("http", {}).get("paths", []):
            yield rule.get("host"), entry


def routes_of(ingress: dict, routes: set[str]) -> set[str]:
    """The app's routes an Ingress sends to the backend."""
    return {
        route
        for _, entry in ingress_paths(ingress)
        for route in routes
        if matches(entry["path"], entry.get("pathType", "Prefix"), route)
    }


def annotation(ingress: dict, name: str) -> str | None:
    """An ingress-nginx annotation of an Ingress, None if it is not set."""
    return ingress["metadata"].get("annotations", {}).get(NGINX + name)


def per_minute(ingress: dict) -> float | None:
    """The requests a minute an Ingress accepts from one client, the stricter of its
    limit-rps and limit-rpm; None without either."""
    rates = []
    if annotation(ingress, "limit-rps") is not None:
        rates.append(60 * float(annotation(ingress, "limit-rps")))
    if annotation(ingress, "limit-rpm") is not None:
        rates.append(float(annotation(ingress, "limit-rpm")))
    return min(rates) if rates else None


def backend_service(ingress: dict) -> set[tuple[str, int | str]]:
    """(Service name, port) of every backend of an Ingress."""
    backends = set()
    for _, entry in ingress_paths(ingress):
        service = entry["backend"]["service"]
        port = service["port"].get("number", service["port"].get("name"))
        backends.add((service["name"], port))
    return backends


def exposed_services(manifests: Manifests) -> dict[str, list[tuple[str, dict]]]:
    """RayService name to the Ingresses whose backend is its Serve Service."""
    names = {service["metadata"]["name"] for _, service in objects(manifests, "RayService")}
    exposed: dict[str, list[tuple[str, dict]]] = {}
    for where, ingress in objects(manifests, "Ingress"):
        for name, _ in backend_service(ingress):
            if name.endswith("-serve-svc") and name.removesuffix("-serve-svc") in names:
                exposed.setdefault(name.removesuffix("-serve-svc"), []).append((where, ingress))
    return exposed


def pod_templates(spec: dict) -> Iterator[tuple[str, dict]]:
    """(group, pod template) of a Ray cluster spec's head and worker groups."""
    yield "head", spec["headGroupSpec"]["template"]
    for group in spec.get("workerGroupSpecs", []):
        yield group["groupName"], group["template"]


def selects(selector: dict, labels: dict) -> bool:
    """Whether a label selector (its matchLabels, or a Service's plain map) selects `labels`."""
    wanted = selector.get("matchLabels", selector) if "matchExpressions" not in selector else None
    return wanted is not None and all(labels.get(k) == v for k, v in wanted.items())


# -- planting a mistake ---------------------------------------------------------------------


#: The files of deploy/ that mistakes are planted in by more than one test file.
PUBLIC, INGRESS = "public/rayservice.yaml", "public/ingress.yaml"


def planted_copy(plant: Plant) -> Manifests:
    """A copy of MANIFESTS with `plant`'s mistake in it."""
    planted = copy.deepcopy(MANIFESTS)
    plant(planted)
    return planted


def edit(manifests: Manifests, file: str, name: str, change: Callable[[dict], None]) -> None:
    """Apply `change` to the object `name` of deploy/`file`."""
    for doc in manifests[f"deploy/{file}"]:
        if doc.get("metadata", {}).get("name") == name:
            change(doc)
            return
    raise AssertionError(f"no {name} in {file}")


def edit_serve(manifests: Manifests, file: str, name: str, change: Callable[[dict], None]) -> None:
    """Apply `change` to the links app of RayService `name`'s serveConfigV2."""

    def rewrite(service: dict) -> None:
        config = yaml.safe_load(service["spec"]["serveConfigV2"])
        change(the_app(config))
        service["spec"]["serveConfigV2"] = yaml.safe_dump(config)

    edit(manifests, file, name, rewrite)


def set_annotation(name: str, value: str | None) -> Callable[[dict], None]:
    """A change setting an Ingress's ingress-nginx annotation `name` to `value` (None: removing
    it)."""

    def change(ingress: dict) -> None:
        annotations = ingress["metadata"]["annotations"]
        if value is None:
            annotations.pop(NGINX + name)
        else:
            annotations[NGINX + name] = value

    return change


def add_path(path: str, path_type: str) -> Callable[[dict], None]:
    """A change adding `path` of `path_type` to an Ingress's first rule, to its first path's
    backend."""

    def change(ingress: dict) -> None:
        paths = ingress["spec"]["rules"][0]["http"]["paths"]
        paths.append({**copy.deepcopy(paths[0]), "path": path, "pathType": path_type})

    return change
