"""The Ray Serve application behind `links serve`: the HTTP API of docs/CONTRACT.md.

| route | answers |
|---|---|
| `GET /api/health` | `{"status": "ok", "paths": <indexed paths>}` |
| `POST /api/simulate` | 200 `{"trajectories"}`, 422 `{"error": "locking", "step", "node"}` |
| `POST /api/retrieve` | 200 `{"results", "took_ms"}`, best first |
| `POST /api/analyze` | 200 the studio's analysis: mobility, dyadic solvability, where it locks |
| `GET /` | the web studio (`links_ray/serve/studio/index.html`) |
| `GET /studio/<file>` | the studio's scripts and style sheet, from the package |

Every bad request gets a 4xx with a JSON `{"error": "<what is wrong>"}`: 400 for malformed
input, 404/405 for unknown routes and methods, 413 for a body over `MAX_BODY_BYTES`, a
mechanism over `MAX_REQUEST_JOINTS` or a simulation over `MAX_REQUEST_JOINT_STEPS`, 415 for a
body that is declared as something other than JSON. The limits and the checks of the values
are the engine's (`links_ray.engine.inputs`, whose ValueErrors become 400s); this module checks
only what JSON alone can get wrong (types, booleans for numbers, array lengths) first. Anything
unexpected is logged by exception type and location only (never a request body) and answered
500 `{"error": "internal error"}`; the replica keeps serving.

Each replica opens the retrieval index once, in its constructor. Retrievals run one at a time
per replica (the index's compiled kernels are parallel, and the JIT's workqueue threading layer,
its fallback without TBB or OpenMP, cannot take concurrent callers), in a worker thread, so
health checks and simulations are answered meanwhile.

`run_server` (what `links serve` runs) starts its own Ray and, with one replica, has the replica
answer HTTP itself, on the port asked for: Ray Serve's *direct ingress*, which its throughput
mode uses. Through Serve's HTTP proxy every request costs about 12 ms more here (an actor hop
and a second one to fetch the body). Serve's proxy then listens on another loopback port.
With several replicas, or on a cluster that Ray was already running, the proxy answers on the
port and balances the replicas.
"""

import functools
import importlib.resources
import json
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response
from ray import serve
from ray.serve.deployment import Application
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from links_ray.data.dataset import open_table
from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_STEPS,
    MAX_BODY_BYTES,
    MAX_REQUEST_JOINT_STEPS,
    MAX_REQUEST_JOINTS,
    as_steps,
    validate_query,
)
from links_ray.engine.mechanism import (
    InvalidMechanismError,
    LockingError,
    analyze_topology,
    dataset_rule_violations,
    mobility,
)
from links_ray.engine.solver import simulate, simulate_until_lock
from links_ray.search.index import RetrievalIndex

logger = logging.getLogger("ray.serve")

#: The studio's files (plain HTML, CSS and JavaScript modules; no build step) and their types.
STUDIO_MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
}
#: Same-origin only: no inline scripts or styles, no third-party requests.
STUDIO_CSP = (
    "default-src 'self'; img-src 'self' data: blob:; object-src 'none'; base-uri 'none'; "
    "form-action 'none'; frame-ancestors 'none'"
)


@functools.cache
def studio_files() -> dict[str, tuple[bytes, str]]:
    """The studio's files by name, as (content, media type), read once from the package."""
    folder = importlib.resources.files("links_ray.serve") / "studio"
    files = {}
    for entry in folder.iterdir():
        media_type = STUDIO_MEDIA_TYPES.get("." + entry.name.rpartition(".")[2])
        if entry.is_file() and media_type is not None:
            files[entry.name] = (entry.read_bytes(), media_type)
    if "index.html" not in files:
        raise FileNotFoundError(f"the studio's index.html is missing from {folder}")
    return files


def studio_response(name: str) -> Response:
    """One studio file, or 404 `{"error"}` for a name the studio does not have."""
    found = studio_files().get(name)
    if found is None:
        raise ApiError(404, f"the studio has no file {name[:80]!r}")
    content, media_type = found
    headers = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}
    if name.endswith(".html"):
        headers["Content-Security-Policy"] = STUDIO_CSP
    return Response(content, media_type=media_type, headers=headers)


class ApiError(Exception):
    """A request the API refuses: its HTTP status and the JSON body's `error` message."""

    def __init__(self, status: int, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.extra = extra


def _jsonable(value: object) -> object:
    """`json.dumps` fallback for numpy scalars and arrays."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


class JsonResponse(JSONResponse):
    """Compact JSON that refuses NaN and infinity and accepts numpy values."""

    def render(self, content: Any) -> bytes:
        """The body: compact JSON, NaN and infinity refused."""
        return json.dumps(
            content, allow_nan=False, separators=(",", ":"), default=_jsonable
        ).encode("utf-8")


def _error(status: int, message: str, **extra: Any) -> JsonResponse:
    return JsonResponse({"error": message, **extra}, status_code=status)


class InternalErrorGuard:
    """ASGI middleware: an exception no handler took becomes 500 `{"error": "internal error"}`.

    Only the exception's type and where it was raised are logged: never its message, which
    may quote the request.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the app; answer 500 if it raises before it has started its response."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception as exc:
            frame = exc.__traceback__
            while frame is not None and frame.tb_next is not None:
                frame = frame.tb_next
            where = f"{frame.tb_frame.f_code.co_filename}:{frame.tb_lineno}" if frame else "unknown"
            logger.error(
                "links-ray API: unexpected %s at %s on %s %s",
                type(exc).__name__,
                where,
                scope.get("method"),
                scope.get("path"),
            )
            if started:
                raise
            await _error(500, "internal error")(scope, receive, send)


api = FastAPI(
    title="links-ray",
    docs_url=None,
    redoc_url=None,
    openapi_url=None,
    default_response_class=JsonResponse,
)
api.add_middleware(InternalErrorGuard)


@api.exception_handler(ApiError)
async def _api_error(request: Request, exc: ApiError) -> JsonResponse:
    return _error(exc.status, exc.message, **exc.extra)


@api.exception_handler(StarletteHTTPException)
async def _http_error(request: Request, exc: StarletteHTTPException) -> JsonResponse:
    response = _error(exc.status_code, str(exc.detail).lower())
    if exc.headers:
        response.headers.update(exc.headers)
    return response


@api.exception_handler(RequestValidationError)
async def _validation_error(request: Request, exc: RequestValidationError) -> JsonResponse:
    problems = [
        f"{'.'.join(str(part) for part in error.get('loc', ()))}: {error.get('msg', 'invalid')}"
        for error in exc.errors()[:5]
    ]
    return _error(400, "invalid request: " + "; ".join(problems))


# -- reading and checking request bodies ------------------------------------------------------


def _kind(value: object) -> str:
    """The JSON type of `value` for messages (never the value: it may be huge)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_finite(value: int | float) -> bool:
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float64
        return False


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number (numbers must be finite)")


async def read_json_object(request: Request) -> dict[str, Any]:
    """The request body as a JSON object, or ApiError (400, 413 or 415) naming the problem."""
    content_type = request.headers.get("content-type")
    if content_type is not None:
        media = content_type.split(";", 1)[0].strip().lower()
        if media and media != "application/json" and not media.endswith("+json"):
            raise ApiError(
                415, f"the body must be JSON (Content-Type application/json), got {media[:80]!r}"
            )
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise ApiError(400, "Content-Length is not a byte count")
        if int(declared) > MAX_BODY_BYTES:
            raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
    chunks: list[bytes] = []
    size = 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > MAX_BODY_BYTES:
                raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
            chunks.append(chunk)
    except ClientDisconnect:  # nobody is left to answer; not a server error
        raise ApiError(400, "the client disconnected before sending the whole body") from None
    body = b"".join(chunks)
    if not body.strip():
        raise ApiError(400, "the body is empty: expected a JSON object")
    try:
        data = json.loads(body, parse_constant=_refuse_constant)
    except UnicodeDecodeError:
        raise ApiError(400, "the body is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise ApiError(
            400, f"the body is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})"
        ) from None
    except ValueError as exc:  # NaN / Infinity, or an integer with too many digits
        raise ApiError(400, f"the body is not valid JSON: {exc}") from None
    except RecursionError:
        raise ApiError(400, "the body is not valid JSON: nested too deeply") from None
    if not isinstance(data, dict):
        raise ApiError(400, f"the body must be a JSON object, got {_kind(data)}")
    return data


def _required(body: dict[str, Any], name: str) -> Any:
    if name not in body:
        raise ApiError(400, f"missing field {name!r}")
    return body[name]


def _checked(check: Callable[..., Any], *args: Any) -> Any:
    """`check(*args)`, an engine validator, with its ValueError answered 400."""
    try:
        return check(*args)
    except ValueError as exc:
        raise ApiError(400, str(exc)) from None


def _numbers(name: str, value: object, count: int, entries: str) -> list:
    """`value` as an array of `count` JSON numbers (not booleans); `entries` says which."""
    if not isinstance(value, list):
        raise ApiError(400, f"{name} must be an array of {count} numbers, got {_kind(value)}")
    if len(value) != count:
        raise ApiError(400, f"{name} must hold {count} entries (one per joint), got {len(value)}")
    for i, entry in enumerate(value):
        if not _is_number(entry):
            raise ApiError(400, f"{name}[{i}] must be {entries}, got {_kind(entry)}")
    return value


def _pairs(name: str, value: object, count: int | None = None) -> list[list[float]]:
    """`value` as a list of finite [x, y] number pairs (`count` of them if given)."""
    if not isinstance(value, list):
        raise ApiError(400, f"{name} must be an array of [x, y] pairs, got {_kind(value)}")
    if count is not None and len(value) != count:
        raise ApiError(
            400, f"{name} must hold {count} [x, y] pairs (one per joint), got {len(value)}"
        )
    for i, pair in enumerate(value):
        if not isinstance(pair, list) or len(pair) != 2:
            what = f"{len(pair)} entries" if isinstance(pair, list) else _kind(pair)
            raise ApiError(400, f"{name}[{i}] must be an [x, y] pair, got {what}")
        for coordinate in pair:
            if not _is_number(coordinate):
                raise ApiError(400, f"{name}[{i}] must hold two numbers, got {_kind(coordinate)}")
            if not _is_finite(coordinate):
                raise ApiError(400, f"{name}[{i}] must hold finite numbers")
    return value


def retrieve_args(body: dict[str, Any]) -> tuple[np.ndarray, int]:
    """The query points (T, 2) and k of a /api/retrieve body, or ApiError naming the problem."""
    points = _pairs("points", _required(body, "points"))
    k = body.get("k")
    return _checked(validate_query, points, DEFAULT_K if k is None else k)


def topology_args(body: dict[str, Any]) -> tuple[list, list]:
    """(adjacency, node_types) of a /api/simulate or /api/analyze body, shapes checked."""
    adjacency = _required(body, "adjacency")
    node_types = _required(body, "node_types")
    if not isinstance(adjacency, list) or not adjacency:
        got = "an empty array" if adjacency == [] else _kind(adjacency)
        raise ApiError(400, f"adjacency must be an n x n array of 0/1, got {got}")
    n = len(adjacency)
    if n > MAX_REQUEST_JOINTS:
        raise ApiError(413, f"at most {MAX_REQUEST_JOINTS} joints per request, got {n}")
    for i, row in enumerate(adjacency):
        _numbers(f"adjacency[{i}]", row, n, "0 or 1")
    _numbers("node_types", node_types, n, "0, 1 or 2")
    return adjacency, node_types


def simulate_args(body: dict[str, Any]) -> tuple[list, list, list, int]:
    """(adjacency, node_types, positions, steps) of a /api/simulate body, shapes checked.

    The engine checks the rest (0/1 links, symmetry, joint types, solvability) and names
    what is wrong.
    """
    adjacency, node_types = topology_args(body)
    n = len(adjacency)
    positions = _pairs("positions", _required(body, "positions"), count=n)
    steps = body.get("steps")
    steps = DEFAULT_STEPS if steps is None else _checked(as_steps, steps)
    if n * steps > MAX_REQUEST_JOINT_STEPS:
        raise ApiError(
            413,
            f"simulation too large: {n} joints x {steps} steps = {n * steps}, "
            f"the limit is {MAX_REQUEST_JOINT_STEPS} joint-steps",
        )
    return adjacency, node_types, positions, steps


def analyze_mechanism(
    adjacency: list, node_types: list, positions: list | None, steps: int
) -> dict[str, Any]:
    """The studio's analysis of a mechanism, from the engine's own checks.

    Always: `joints`, `moving`, `links`, `dof` (2 x moving - links), `solvable` (dyadic),
    `problem` (the engine's message, or None), `order` (the solution path as [joint, a, b]
    rows) and `dataset_rules` (the dataset rules it breaks: docs/CONTRACT.md, Mechanisms).
    With positions and a solvable topology also `lock` (None, or `step`, `node` and `angle`,
    the crank's turn in degrees) and, when it locks, `trajectories` [n][step][2] of the steps
    before the lock.
    Raises InvalidMechanismError for degenerate positions, as /api/simulate does.
    """
    moving, links, dof = mobility(adjacency, node_types)
    found: dict[str, Any] = {"joints": len(node_types), "moving": moving, "links": links}
    found["dof"] = dof
    try:
        topology = analyze_topology(adjacency, node_types)
    except InvalidMechanismError as exc:
        return {**found, "solvable": False, "problem": str(exc), "order": [], "lock": None}
    found.update(solvable=True, problem=None, order=topology.order.tolist(), lock=None)
    pose = None if positions is None else np.asarray(positions, dtype=np.float64)
    found["dataset_rules"] = dataset_rule_violations(topology, pose)
    if positions is not None:
        trajectories, step, node = simulate_until_lock(adjacency, node_types, positions, steps)
        if step >= 0:
            found["lock"] = {"step": step, "node": node, "angle": 360.0 * step / steps}
            found["trajectories"] = trajectories.tolist()
    return found


def _simulate_lists(adjacency: list, node_types: list, positions: list, steps: int) -> list:
    return simulate(adjacency, node_types, positions, steps).tolist()


# -- the deployment -----------------------------------------------------------------------------


#: Ray starts worker processes at niceness 15, below its own control plane (GCS, raylet,
#: dashboard agent) at 0. A replica answers users, and its parallel kernels wait for their
#: slowest thread, so it runs at 0: in-replica time per retrieval fell from about 46 to 42 ms.
REPLICA_ENV = {"RAY_worker_niceness": "0"}


@serve.deployment(
    name="LinksApi",
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
@serve.ingress(api)
class LinksApi:
    """The HTTP API of one replica: the retrieval index of `root`, opened once."""

    def __init__(self, root: str) -> None:
        self.root = root
        self.index = RetrievalIndex.open(root)
        self.index.warm()  # also loads the solver /api/simulate uses
        self._retrieving = threading.Lock()
        studio_files()  # a package without the studio fails here, not on a user's first visit

    @api.get("/", response_class=HTMLResponse)
    async def api_studio(self) -> Response:
        """The web studio's page."""
        return studio_response("index.html")

    @api.get("/studio/{name}")
    async def api_studio_file(self, name: str) -> Response:
        """One of the studio's scripts or its style sheet; 404 for any other name."""
        return studio_response(name)

    @api.get("/api/health")
    async def api_health(self) -> JsonResponse:
        """`{"status": "ok", "paths": <indexed paths>}`."""
        return JsonResponse({"status": "ok", "paths": len(self.index)})

    @api.post("/api/simulate")
    async def api_simulate(self, request: Request) -> Response:
        """Trajectories [n][steps][2] of a mechanism, 422 if it locks, 4xx if malformed."""
        args = simulate_args(await read_json_object(request))
        try:
            trajectories = await run_in_threadpool(_simulate_lists, *args)
        except LockingError as exc:
            return _error(422, "locking", step=exc.step, node=exc.node)
        except ValueError as exc:  # InvalidMechanismError names the problem
            raise ApiError(400, str(exc)) from None
        return JsonResponse({"trajectories": trajectories})

    @api.post("/api/analyze")
    async def api_analyze(self, request: Request) -> JsonResponse:
        """Degree of freedom, dyadic solvability and, given positions, where it locks."""
        body = await read_json_object(request)
        if body.get("positions") is None:
            adjacency, node_types = topology_args(body)
            args = (adjacency, node_types, None, DEFAULT_STEPS)
        else:
            args = simulate_args(body)
        try:
            found = await run_in_threadpool(analyze_mechanism, *args)
        except ValueError as exc:  # degenerate positions: named as /api/simulate names them
            raise ApiError(400, str(exc)) from None
        return JsonResponse(found)

    @api.post("/api/retrieve")
    async def api_retrieve(self, request: Request) -> JsonResponse:
        """The k curated paths nearest to a drawn curve, best first, with their mechanisms."""
        points, k = retrieve_args(await read_json_object(request))
        start = time.perf_counter()
        try:
            results = await run_in_threadpool(self._retrieve, points, k)
        except ValueError as exc:
            raise ApiError(400, str(exc)) from None
        took_ms = (time.perf_counter() - start) * 1e3
        return JsonResponse({"results": results, "took_ms": round(took_ms, 3)})

    def _retrieve(self, points: np.ndarray, k: int) -> list[dict]:
        with self._retrieving:
            return self.index.retrieve(points, k)


def check_root(root: str) -> None:
    """Fail early, with ValueError naming the problem, if `root` has no curated table."""
    open_table(root, "curated")


def build_app(root: str, replicas: int = 1) -> Application:
    """The Serve application for dataset `root` with `replicas` replicas (not yet running)."""
    if isinstance(replicas, bool) or not isinstance(replicas, int) or replicas < 1:
        raise ValueError(f"replicas must be a positive integer, got {replicas!r}")
    return LinksApi.options(num_replicas=replicas).bind(root)


def app_builder(args: dict[str, Any]) -> Application:
    """Application builder for Serve config files: args `root` (required) and `replicas`."""
    if "root" not in args or not str(args["root"]).strip():
        raise ValueError("the links application needs args.root: a dataset folder or s3://...")
    unknown = sorted(set(args) - {"root", "replicas"})
    if unknown:
        raise ValueError(f"unknown args for the links application: {unknown}")
    replicas = args.get("replicas", 1)
    if isinstance(replicas, str) and replicas.strip().isdigit():
        replicas = int(replicas)  # `serve run ... replicas=2` passes strings
    if isinstance(replicas, bool) or not isinstance(replicas, int):
        raise ValueError(f"args.replicas must be a positive integer, got {replicas!r}")
    check_root(str(args["root"]))
    return build_app(str(args["root"]), replicas)


def direct_ingress_env(port: int) -> dict[str, str]:
    """The environment under which Ray Serve's HTTP ingress replica serves on `port` itself.

    Ray reads it when it starts (its controller and replicas inherit it). A released port is
    taken back at once, so a restarted replica answers on the same port; and a stopping
    replica drains for a second, not 30: there is no load balancer in front to leave.
    """
    return {
        "RAY_SERVE_ENABLE_DIRECT_INGRESS": "1",
        "RAY_SERVE_DIRECT_INGRESS_MIN_HTTP_PORT": str(port),
        "RAY_SERVE_DIRECT_INGRESS_MAX_HTTP_PORT": str(port + 1),  # exclusive
        "RAY_SERVE_PORT_QUARANTINE_S": "0",
        "RAY_SERVE_DIRECT_INGRESS_MIN_DRAINING_PERIOD_S": "1",
    }


def bindable_port(host: str, port: int) -> int:
    """`port` (a free one if 0) if it can be bound on `host`, else ValueError naming why."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            # As servers bind: connections that just closed do not hold the port.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
            return probe.getsockname()[1]
    except OSError as exc:
        raise ValueError(f"cannot serve on {host} port {port}: {exc.strerror}") from None


def run_server(
    root: str,
    host: str = "127.0.0.1",
    port: int = 8000,
    replicas: int = 1,
    blocking: bool = True,
) -> None:
    """Serve `root` on http://host:port/ (Ray local unless RAY_ADDRESS) until Ctrl-C.

    When this call starts Ray and serves one replica, the replica answers on `port` directly
    (`direct_ingress_env`) and Serve's proxy takes a free port; otherwise the proxy answers.
    """
    import ray

    from links_ray.cluster.connect import connect

    check_root(root)  # a wrong ROOT is one line here, not a replica failing to start
    app = build_app(root, replicas)
    direct = replicas == 1 and not ray.is_initialized() and not os.environ.get("RAY_ADDRESS")
    proxy_port = port
    if direct:
        bindable_port(host, port)  # else the replica retries and fails without saying why
        os.environ.update(direct_ingress_env(port))
        proxy_port = bindable_port(host, 0)
    connect()
    no_access_log = {"enable_access_log": False}
    serve.start(http_options={"host": host, "port": proxy_port}, logging_config=no_access_log)
    try:
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
    except BaseException:
        serve.shutdown()
        raise
    shown = f"[{host}]" if ":" in host else host
    print(f"links-ray: serving {root} at http://{shown}:{port}/ (API under /api)", flush=True)
    if not blocking:
        return
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("links-ray: shutting down", flush=True)
    finally:
        serve.shutdown()
