"""The manifests under deploy/ against the code they run, without a cluster.

Every YAML file parses; every Serve config builds the links app with args it takes; every
Ingress routes only routes the app has, each route through exactly one of them, with TLS, rate
limits, the app's body limit and timeouts; every route but the open ones behind one login and
the quota service, which gives each a per-user quota and a global cap (and, run here over HTTP,
enforces them); NetworkPolicies let only the ingress controller reach a public RayService's
Serve port and only its own pods its Ray ports; a RayService behind an Ingress holds only the
read-only keys, whose policy only reads, and names the Ingress's hosts in its allow-list; the
RayJobs run real `links` commands that generate, curate and index every root a RayService
serves, as it serves it. Each check returns the problems it finds, and
`test_a_planted_mistake_is_found` shows each one finding a mistake planted in a copy.
(tests/serve/test_serve.py checks the private Serve config's and RayService's own values.)
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import re
import shlex
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml

from links_ray.engine.synthesis.options import MAX_SYNTHESIS_SECONDS
from links_ray.serve.app import APP_ARGS, PARTITION_CPUS, _arg
from links_ray.serve.deployments import REPLICA_ENV, SHUTDOWN_DRAIN_S, LinksApi
from links_ray.serve.http.limits import MAX_BODY_BYTES, PARTITION_TIMEOUT_S
from links_ray.serve.http.middleware import as_host_names

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"

#: Documents of each YAML file under deploy/, by path from the repository root.
Manifests = dict[str, list[Any]]

APP_BUILDER = "links_ray.serve.app:app_builder"
#: The Secrets of S3 keys: the writer's (generation, curation, the index) and the reader's
#: (the pods of a public RayService).
WRITER_SECRET, READER_SECRET = "links-s3-credentials", "links-s3-reader"
#: The MinIO policy files in the ConfigMap of deploy/minio/minio.yaml.
WRITER_POLICY, READER_POLICY = "links-readwrite", "links-readonly"
#: All a reader may do: list the bucket and get its objects.
READ_ACTIONS = {"s3:GetObject", "s3:ListBucket", "s3:GetBucketLocation"}
SYNTHESIZE = "/api/synthesize"
NGINX = "nginx.ingress.kubernetes.io/"
#: The routes anyone may ask without a login: the studio's page and files, and what computes
#: nothing (health, the request limits, the OpenAPI document). Every other route costs.
OPEN_ROUTES = {"/", "/studio/{name}", "/api/health", "/api/limits", "/openapi.json"}
#: The quota service's name (its ConfigMap, Deployment, Service and pod label).
QUOTA = "links-quota"
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
#: Shell operators in an entrypoint, as `shlex` splits them with punctuation_chars.
SHELL_OPERATORS = {"&&", "||", ";", "|", "&", ";;", "(", ")", "<", ">", ">>", "<<"}
#: Ray's logical CPUs of a RayService's replicas: the gateway's unless the config says otherwise.
GATEWAY_CPUS = float(LinksApi.ray_actor_options["num_cpus"])


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


def nginx_size(text: str) -> int | None:
    """Bytes of an nginx size ("2m": 2 MiB; nginx's k, m and g are powers of 1024)."""
    found = re.fullmatch(r"(\d+)([kKmMgG]?)", text.strip())
    if found is None:
        return None
    return int(found[1]) * 1024 ** " kmg".index(found[2].lower() or " ")


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


def secrets_named(value: Any) -> set[str]:
    """Names of the Secrets a pod spec (or any part of one) reads: keys of env, envFrom and
    volumes."""
    found: set[str] = set()
    if isinstance(value, dict):
        for key, inner in value.items():
            if key in ("secretKeyRef", "secretRef") and isinstance(inner, dict):
                found.add(inner.get("name"))
            elif key == "secret" and isinstance(inner, dict):
                found.add(inner.get("secretName"))
            else:
                found |= secrets_named(inner)
    elif isinstance(value, list):
        for inner in value:
            found |= secrets_named(inner)
    return found


def cpus(quantity: str | float | int) -> float:
    """A Kubernetes CPU quantity ("16", "500m") in CPUs."""
    text = str(quantity)
    return float(text[:-1]) / 1000 if text.endswith("m") else float(text)


def shell_words(text: str) -> list[str]:
    """`text` split as a POSIX shell splits it, operators as words of their own."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    return list(lexer)


def entrypoint_commands(entrypoint: str, env: dict[str, str]) -> tuple[list[list[str]], list[str]]:
    """The commands a RayJob's entrypoint runs, each as its words ($NAME and ${NAME} replaced
    by `env`), and the problems with it.

    KubeRay's submitter runs `ray job submit ... -- ENTRYPOINT ; ...` in a shell, so a bare
    operator in ENTRYPOINT would split the submission there and run the rest in the
    submitter's pod: a chain must be one argument of `bash -c` (or `sh -c`), joined by `&&`
    only, so that a failed step ends the job."""
    problems: list[str] = []

    def expand(word: str) -> str:
        def value(found: re.Match[str]) -> str:
            name = found[1] or found[2]
            if name not in env:
                problems.append(f"${name} is set nowhere in the head's env")
            return env.get(name, "")

        return re.sub(r"\$\{(\w+)\}|\$(\w+)", value, word)

    words = shell_words(entrypoint)
    if SHELL_OPERATORS & set(words):
        problems.append(
            f"{entrypoint!r}: the submitter's shell would run what follows "
            f"{sorted(SHELL_OPERATORS & set(words))} itself; chain commands in bash -c '...'"
        )
        return [], problems
    if words[:2] in (["bash", "-c"], ["sh", "-c"]) and len(words) == 3:
        words = shell_words(words[2])
    commands: list[list[str]] = [[]]
    for word in words:
        if word == "&&":
            commands.append([])
        elif word in SHELL_OPERATORS:
            problems.append(f"{entrypoint!r}: chain commands with && only, not {word!r}")
        else:
            commands[-1].append(expand(word))
    return [command for command in commands if command], problems


def parse_links(words: list[str]) -> tuple[Any, str | None]:
    """`links ARGS` parsed by the command line's own parser: (its namespace, None), or (None,
    the parser's complaint)."""
    from links_ray.cli.main import build_parser

    if words[:1] != ["links"]:
        return None, f"{shlex.join(words)!r} is not a links command"
    complaint = io.StringIO()
    try:
        with contextlib.redirect_stderr(complaint), contextlib.redirect_stdout(io.StringIO()):
            return build_parser().parse_args(words[1:]), None
    except SystemExit:
        return None, f"{shlex.join(words)!r}: {complaint.getvalue().strip()}"


def job_steps(manifests: Manifests) -> tuple[dict[str, list[Any]], list[str]]:
    """The `links` commands of each RayJob, parsed, in order; and the problems found."""
    steps: dict[str, list[Any]] = {}
    problems = []
    for where, job in objects(manifests, "RayJob"):
        head = job["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]
        env = {
            item["name"]: str(item["value"])
            for container in head["containers"]
            for item in container.get("env", [])
            if "value" in item
        }
        commands, found = entrypoint_commands(job["spec"]["entrypoint"], env)
        problems += [f"{where}: {problem}" for problem in found]
        steps[where] = []
        for words in commands:
            parsed, complaint = parse_links(words)
            if complaint:
                problems.append(f"{where}: {complaint}")
            else:
                steps[where].append(parsed)
    return steps, problems


def root_of(parsed: Any) -> str:
    """The dataset root a parsed `links generate`, `curate` or `index` works on."""
    return (parsed.out if parsed.command == "generate" else parsed.root).rstrip("/")


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


def named(manifests: Manifests, kind: str, name: str) -> tuple[str, dict] | None:
    """(where, object) of the object `name` of `kind`, None if there is none."""
    found = [(w, o) for w, o in objects(manifests, kind) if o["metadata"]["name"] == name]
    return found[0] if found else None


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


def selects(selector: dict, labels: dict) -> bool:
    """Whether a label selector (its matchLabels, or a Service's plain map) selects `labels`."""
    wanted = selector.get("matchLabels", selector) if "matchExpressions" not in selector else None
    return wanted is not None and all(labels.get(k) == v for k, v in wanted.items())


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


def policies(manifests: Manifests) -> dict[str, dict]:
    """The MinIO policies of the ConfigMap that holds them, by name."""
    found = {}
    for _, config_map in objects(manifests, "ConfigMap"):
        for name, text in config_map.get("data", {}).items():
            if name.endswith(".json") and name.removesuffix(".json") in (
                WRITER_POLICY,
                READER_POLICY,
            ):
                found[name.removesuffix(".json")] = json.loads(text)
    return found


def allowed(policy: dict) -> dict[str, set[str]]:
    """Action to the resources an IAM policy allows it on."""
    granted: dict[str, set[str]] = {}
    for statement in policy["Statement"]:
        actions = statement["Action"]
        resources = statement["Resource"]
        for action in [actions] if isinstance(actions, str) else actions:
            granted.setdefault(action, set()).update(
                [resources] if isinstance(resources, str) else resources
            )
    return granted


def key_problems(manifests: Manifests) -> list[str]:
    """A RayService behind an Ingress holds only the reader's keys, whose policy lets it list
    and read the served bucket and nothing else; the RayJobs' Ray pods hold the writer's,
    whose policy writes, and their submitters none; the bucket Job gives each key pair its
    policy."""
    problems = []
    exposed = exposed_services(manifests)
    for where, service in objects(manifests, "RayService"):
        if service["metadata"]["name"] not in exposed:
            continue  # private: it may build and save its own index (RUNBOOK.md, section 6)
        for group, template in pod_templates(service["spec"]["rayClusterConfig"]):
            held = secrets_named(template["spec"])
            if held != {READER_SECRET}:
                problems.append(
                    f"{where}: public {group} pods hold {sorted(held)}, not only {READER_SECRET}"
                )
    templates = {secret["metadata"]["name"] for _, secret in objects(manifests, "Secret")}
    for name in sorted({WRITER_SECRET, READER_SECRET} - templates):
        problems.append(f"no template of the Secret {name} under deploy/")
    for where, job in objects(manifests, "RayJob"):
        for group, template in pod_templates(job["spec"]["rayClusterSpec"]):
            held = secrets_named(template["spec"])
            if held != {WRITER_SECRET}:
                problems.append(f"{where}: {group} pods hold {sorted(held)}, not {WRITER_SECRET}")
        submitter = job["spec"].get("submitterPodTemplate", {})
        if secrets_named(submitter):
            problems.append(f"{where}: the submitter holds {sorted(secrets_named(submitter))}")
    found = policies(manifests)
    if set(found) != {WRITER_POLICY, READER_POLICY}:
        return [*problems, f"policies {sorted(found)}, not {WRITER_POLICY} and {READER_POLICY}"]
    buckets = {
        root.removeprefix("s3://").split("/")[0]
        for _, config in serve_configs(manifests)
        if (root := str(the_app(config).get("args", {}).get("root", ""))).startswith("s3://")
    }
    arns = {f"arn:aws:s3:::{bucket}" for bucket in buckets}
    arns |= {f"{arn}/*" for arn in arns}
    reader, writer = allowed(found[READER_POLICY]), allowed(found[WRITER_POLICY])
    if any(s["Effect"] != "Allow" for s in found[READER_POLICY]["Statement"]):
        problems.append(f"{READER_POLICY}: only Allow statements can be checked here")
    for action, resources in reader.items():
        if action not in READ_ACTIONS:
            problems.append(f"{READER_POLICY} allows {action}: it may only list and read")
        if not resources <= arns:
            problems.append(f"{READER_POLICY} allows {action} on {sorted(resources - arns)}")
    for action in ("s3:GetObject", "s3:ListBucket"):
        if action not in reader:
            problems.append(f"{READER_POLICY} lacks {action}, which serving needs")
    for action in ("s3:GetObject", "s3:ListBucket", "s3:PutObject", "s3:DeleteObject"):
        if action not in writer:
            problems.append(f"{WRITER_POLICY} lacks {action}, which the jobs need")
    problems += bucket_job_problems(manifests)
    return problems


def bucket_job_problems(manifests: Manifests) -> list[str]:
    """The bucket Job attaches the writer's policy to the writer's keys and the reader's to
    the reader's (the env var its script names, read from which Secret)."""
    problems = []
    for where, job in objects(manifests, "Job"):
        (container,) = job["spec"]["template"]["spec"]["containers"]
        script = "\n".join(container.get("args", []))
        if "mc admin policy" not in script:
            continue
        secret_of = {
            item["name"]: item["valueFrom"]["secretKeyRef"]["name"]
            for item in container.get("env", [])
            if "secretKeyRef" in item.get("valueFrom", {})
        }
        attached = {
            secret_of.get(variable): policy
            for variable, policy in re.findall(
                r'user_with_policy "\$(\w+)" "\$\w+" (links-[\w-]+)', script
            )
        }
        wanted = {WRITER_SECRET: WRITER_POLICY, READER_SECRET: READER_POLICY}
        if attached != wanted:
            problems.append(f"{where}: attaches {attached}, not {wanted}")
    return problems


def job_problems(manifests: Manifests) -> list[str]:
    """Every RayJob entrypoint runs real `links` commands, and for every root a RayService
    serves, one job generates it and one curates it and then saves its index split as the
    RayService serves it."""
    steps, problems = job_steps(manifests)
    for where, service in objects(manifests, "RayService"):
        args = the_app(yaml.safe_load(service["spec"]["serveConfigV2"])).get("args", {})
        root = str(args["root"]).rstrip("/")
        shards = args.get("shards")
        if not any(
            step.command == "generate" and root_of(step) == root
            for done in steps.values()
            for step in done
        ):
            problems.append(f"{where}: no RayJob generates {root}")
        indexed = False
        for done in steps.values():
            for place, step in enumerate(done):
                if step.command == "index" and root_of(step) == root and step.shards == shards:
                    curated = any(
                        s.command == "curate" and root_of(s) == root for s in done[:place]
                    )
                    indexed = indexed or curated
        if not indexed:
            split = f"--shards {shards}" if shards else "no --shards"
            problems.append(
                f"{where}: no RayJob curates {root}, then runs links index with {split}"
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


def test_ingresses_route_the_app_with_tls_limits_and_the_body_limit() -> None:
    assert len(objects(MANIFESTS, "Ingress")) >= 2
    assert ingress_problems(MANIFESTS) == []


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


def test_network_policies_guard_the_serve_and_ray_ports() -> None:
    assert objects(MANIFESTS, "NetworkPolicy")
    assert network_problems(MANIFESTS) == []


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


def test_public_pods_hold_read_only_keys_and_jobs_the_writers() -> None:
    assert exposed_services(MANIFESTS)  # a RayService behind an Ingress, checked
    assert key_problems(MANIFESTS) == []


def test_jobs_run_links_commands_that_make_every_served_root() -> None:
    steps, _ = job_steps(MANIFESTS)
    commands = {step.command for done in steps.values() for step in done}
    assert {"generate", "curate", "index"} <= commands
    assert job_problems(MANIFESTS) == []


# -- each check finds a planted mistake -----------------------------------------------------


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
    def change(ingress: dict) -> None:
        annotations = ingress["metadata"]["annotations"]
        if value is None:
            annotations.pop(NGINX + name)
        else:
            annotations[NGINX + name] = value

    return change


def add_path(path: str, path_type: str) -> Callable[[dict], None]:
    def change(ingress: dict) -> None:
        paths = ingress["spec"]["rules"][0]["http"]["paths"]
        paths.append({**copy.deepcopy(paths[0]), "path": path, "pathType": path_type})

    return change


def worker_env(secret: str) -> Callable[[dict], None]:
    def change(service: dict) -> None:
        group = service["spec"]["rayClusterConfig"]["workerGroupSpecs"][0]
        (container,) = group["template"]["spec"]["containers"]
        container["env"][-1]["valueFrom"]["secretKeyRef"]["name"] = secret

    return change


def entrypoint(text: str) -> Callable[[dict], None]:
    def change(job: dict) -> None:
        job["spec"]["entrypoint"] = text

    return change


def reader_policy_allows(action: str) -> Callable[[dict], None]:
    def change(config_map: dict) -> None:
        policy = json.loads(config_map["data"][f"{READER_POLICY}.json"])
        policy["Statement"][-1]["Action"].append(action)
        config_map["data"][f"{READER_POLICY}.json"] = json.dumps(policy)

    return change


def in_script(old: str, new: str) -> Callable[[dict], None]:
    def change(job: dict) -> None:
        (container,) = job["spec"]["template"]["spec"]["containers"]
        assert old in container["args"][0]
        container["args"][0] = container["args"][0].replace(old, new)

    return change


def gateway_override(change_options: Callable[[dict], None]) -> Callable[[dict], None]:
    def change(app: dict) -> None:
        change_options(app["deployments"][0]["ray_actor_options"])

    return change


def set_quota(route: str, limit: dict | None) -> Callable[[dict], None]:
    def change(config_map: dict) -> None:
        limits = json.loads(config_map["data"]["quotas.json"])
        if limit is None:
            limits.pop(route)
        else:
            limits[route] = limit
        config_map["data"]["quotas.json"] = json.dumps(limits)

    return change


def policy_rule(index: int, change_rule: Callable[[dict], None]) -> Callable[[dict], None]:
    def change(policy: dict) -> None:
        change_rule(policy["spec"]["ingress"][index])

    return change


PUBLIC, INGRESS, MINIO = "public/rayservice.yaml", "public/ingress.yaml", "minio/minio.yaml"
QUOTAS, POLICIES = "public/quota.yaml", "public/networkpolicy.yaml"
INDEX_JOB = "kuberay/rayjob-index.yaml"
#: (check, the mistake planted, a phrase of the problem it must report).
PLANTED: list[tuple[Callable[[Manifests], list[str]], Callable[[Manifests], None], str]] = [
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
        ingress_problems,
        lambda m: edit(m, INGRESS, "links-public", add_path("/api", "Prefix")),
        "routed by 2 paths",
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
    (
        key_problems,
        lambda m: edit(m, PUBLIC, "links-public", worker_env(WRITER_SECRET)),
        "not only links-s3-reader",
    ),
    (
        key_problems,
        lambda m: edit(m, MINIO, "minio-policies", reader_policy_allows("s3:PutObject")),
        "allows s3:PutObject",
    ),
    (
        key_problems,
        lambda m: edit(m, MINIO, "minio-policies", reader_policy_allows("s3:*")),
        "allows s3:*",
    ),
    (
        key_problems,
        lambda m: edit(
            m,
            MINIO,
            "minio-create-bucket",
            in_script(
                '"$READER_SECRET_ACCESS_KEY" links-readonly',
                '"$READER_SECRET_ACCESS_KEY" links-readwrite',
            ),
        ),
        "attaches",
    ),
    (
        job_problems,
        lambda m: edit(
            m, INDEX_JOB, "links-index", entrypoint("bash -c 'links indx s3://links/dataset'")
        ),
        "invalid choice: 'indx'",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint(
                "links curate s3://links/dataset && links index s3://links/dataset --shards 32"
            ),
        ),
        "the submitter's shell would run",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint(
                "bash -c 'links curate s3://links/dataset && "
                "links index s3://links/dataset --shards 16'"
            ),
        ),
        "then runs links index with --shards 32",
    ),
    (
        job_problems,
        lambda m: edit(
            m,
            INDEX_JOB,
            "links-index",
            entrypoint("bash -c 'links index s3://links/dataset --shards 32'"),
        ),
        "no RayJob curates s3://links/dataset",
    ),
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
def test_a_planted_mistake_is_found(
    check: Callable[[Manifests], list[str]], plant: Callable[[Manifests], None], phrase: str
) -> None:
    planted = copy.deepcopy(MANIFESTS)
    plant(planted)
    found = check(planted)
    assert any(phrase in problem for problem in found), found
