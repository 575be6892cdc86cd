"""The routes of the HTTP API: what each one answers, and the work behind it.

| route | answers |
|---|---|
| `GET /api/health` | `{"status": "ok", "paths": <indexed paths>}`; partitioned also `"shards"` |
| `POST /api/simulate` | 200 `{"trajectories"}`, 422 `{"error": "locking", "step", "node"}` |
| `POST /api/retrieve` | 200 `{"results", "took_ms"}`, best first; 503 when busy |
| `POST /api/synthesize` | 200 `{"results", "took_ms", "queued_ms"}`, refined; 503 when busy |
| `POST /api/analyze` | 200 the studio's analysis: mobility, dyadic solvability, where it locks |
| `POST /api/export` | 200 the mechanism as an SVG, DXF or table file in mm (an attachment) |
| `POST /api/curve` | 200 `{"points", "closed"}`: a drawing's curve, read in a reader process |
| `POST /api/kit` | 200 a mechanism's printable parts: its bill (JSON), GLB or a zip |
| `GET /api/limits` | the limits a request meets (`serve.http.limits.request_limits`) |
| `GET /openapi.json` | the API described, bodies and bounds included (`serve.http.openapi`) |
| `GET /` | the web studio (`links_ray/serve/studio/index.html`) |
| `GET /studio/<file>` | the studio's scripts, style sheet and vendored files, from the package |

The routes are methods of `LinksApiRoutes`, declared on `router`, which the app
(`serve.http.asgi`) takes in; the gateway deployment `LinksApi` (`serve.deployments`) inherits
them and gives them the index behind them, a `serve.http.backend.RetrievalBackend`, and the
admission (`serve.http.admission`) whose places these routes claim and release. This module
imports neither the app nor the deployments: the assembly imports the routes, never the other
way. Bodies are read and checked by `serve.http.bodies`; simulations, analyses and exports run
in the default thread pool, builds of parts in one thread of their own (`serve.http.kits`),
refinements of syntheses in the gateway's refinement thread, stopped when
their client goes (`serve.http.synthesis_run`).
"""

import asyncio
import functools
import importlib.resources
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from links_ray.engine.fabrication.drawings import Fabrication, fabrication
from links_ray.engine.kinematics.mechanism import (
    InvalidMechanismError,
    LockingError,
    analyze_topology,
    dataset_rule_violations,
    mobility,
)
from links_ray.engine.kinematics.solver import simulate, simulate_until_lock
from links_ray.engine.synthesis.options import MAX_SYNTHESIS_SECONDS
from links_ray.engine.synthesis.plan import retrievals
from links_ray.interop.curve_worker import CurveReadersBusy
from links_ray.interop.drawings import dxf_drawing, svg_drawing
from links_ray.serve.http import kit_schemas, schemas
from links_ray.serve.http.admission import Admission, Place
from links_ray.serve.http.backend import RetrievalBackend
from links_ray.serve.http.bodies import EXPORT_FORMATS, KIT_FORMATS, read_route_args
from links_ray.serve.http.kits import answer_kit
from links_ray.serve.http.limits import request_limits
from links_ray.serve.http.responses import (
    ApiError,
    JsonResponse,
    error_response,
    json_answer,
)
from links_ray.serve.http.schemas import request_body
from links_ray.serve.http.synthesis_run import (
    start_refinement,
    synthesis_answer,
    synthesis_lines,
    unless_gone,
)

#: The routes, as methods of `LinksApiRoutes`; the app (`serve.http.asgi`) takes them in.
router = APIRouter()

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


#: Third-party files, unchanged, one folder per package and version (`studio/vendor/README.md`).
STUDIO_VENDOR = "vendor"


@functools.cache
def studio_files() -> dict[str, tuple[bytes, str]]:
    """The studio's files by name, as (content, media type), read once from the package: its
    own by file name, the vendored ones by their path (`vendor/three-0.187.0/three.module.js`).
    A name is looked up here, never joined to a path on disk."""
    folder = importlib.resources.files("links_ray.serve") / "studio"
    files = {}
    pending = [("", folder)]
    while pending:
        prefix, here = pending.pop()
        for entry in here.iterdir():
            name = prefix + entry.name
            if entry.is_dir() and name.startswith(STUDIO_VENDOR):
                pending.append((name + "/", entry))
                continue
            media_type = STUDIO_MEDIA_TYPES.get("." + entry.name.rpartition(".")[2])
            if entry.is_file() and media_type is not None:
                files[name] = (entry.read_bytes(), media_type)
    if "index.html" not in files:
        raise FileNotFoundError(f"the studio's index.html is missing from {folder}")
    return files


def studio_response(name: str) -> Response:
    """One studio file, or 404 `{"error"}` for a name the studio does not have."""
    found = studio_files().get(name)
    if found is None:
        raise ApiError(404, f"the studio has no file {name[:80]!r}")
    content, media_type = found
    # The studio's own files change with the package; a vendored file's path names its
    # version, so its content never changes and a browser may keep it.
    vendored = name.startswith(STUDIO_VENDOR + "/")
    cache = "public, max-age=31536000, immutable" if vendored else "no-cache"
    headers = {"Cache-Control": cache, "X-Content-Type-Options": "nosniff"}
    if name.endswith(".html"):
        headers["Content-Security-Policy"] = STUDIO_CSP
    return Response(content, media_type=media_type, headers=headers)


def analyze_mechanism(
    adjacency: list, node_types: list, positions: list | None, steps: int
) -> dict[str, Any]:
    """The studio's analysis of a mechanism, from the engine's own checks.

    Always: `joints`, `moving`, `links`, `dof` (2 x moving - links), `solvable` (dyadic),
    `problem` (the engine's message, or None), `order` (the solution path as [joint, a, b]
    rows) and `dataset_rules` (the dataset rules it breaks: docs/reference/contract.md, Mechanisms).
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
            found["trajectories"] = trajectories  # rendered in pieces (`json_answer`)
    return found


def export_file(
    adjacency: list,
    node_types: list,
    positions: list,
    chosen: str,
    crank_mm: float,
    path_joint: Any,
) -> Response:
    """The mechanism as a file to download (engine.fabrication.drawings, written by
    interop.drawings), or ValueError naming why not."""
    drawing = fabrication(adjacency, node_types, positions, crank_mm, path_joint)
    writers = {"svg": svg_drawing, "dxf": dxf_drawing, "table": Fabrication.table_text}
    text = writers[chosen](drawing)
    media_type, suffix = EXPORT_FORMATS[chosen]
    name = f"mechanism-{len(node_types)}-joints-{crank_mm:g}mm.{suffix}"
    return Response(
        text,
        media_type=media_type,
        headers={
            "Content-Disposition": f'attachment; filename="{name}"',
            "X-Content-Type-Options": "nosniff",
        },
    )


class LinksApiRoutes:
    """The routes of the HTTP API, as methods of the gateway deployment `LinksApi`
    (`serve.deployments`), which inherits them and gives them what they use: the index behind
    them (`_backend`, a `RetrievalBackend`: one index, or its partitions), its admission of
    retrievals and syntheses (`_admission`) and its refinement thread (`_refining`)."""

    _backend: RetrievalBackend
    _admission: Admission
    _refining: ThreadPoolExecutor

    @router.get("/", response_class=HTMLResponse)
    async def api_studio(self) -> Response:
        """The web studio's page."""
        return studio_response("index.html")

    @router.get("/studio/{name:path}")
    async def api_studio_file(self, name: str) -> Response:
        """One of the studio's scripts, its style sheet or a vendored file
        (`vendor/<package>-<version>/<file>`); 404 for any other name."""
        return studio_response(name)

    @router.get("/api/health", response_model=schemas.HealthResponse)
    async def api_health(self) -> JsonResponse:
        """`{"status": "ok", "paths": <indexed paths>}`, and with partitions their paths."""
        return JsonResponse({"status": "ok", **await self._backend.health()})

    @router.get("/api/limits", response_model=schemas.LimitsResponse)
    async def api_limits(self) -> JsonResponse:
        """The limits every request meets (the studio reads its own from here)."""
        return JsonResponse(request_limits())

    @router.post(
        "/api/simulate",
        response_model=schemas.SimulateResponse,
        responses={
            422: {"model": schemas.LockingResponse, "description": "it locks"},
            **schemas.error_responses(400, 413, 415),
        },
        openapi_extra=request_body("/api/simulate"),
    )
    async def api_simulate(self, request: Request) -> Response:
        """Trajectories [n][steps][2] of a mechanism, 422 if it locks, 4xx if malformed."""
        args = await read_route_args(request, "/api/simulate")
        try:
            trajectories = await run_in_threadpool(simulate, *args)
        except LockingError as exc:
            return error_response(422, "locking", step=exc.step, node=exc.node)
        except ValueError as exc:  # InvalidMechanismError names the problem
            raise ApiError(400, str(exc)) from None
        return await json_answer({"trajectories": trajectories})

    @router.post(
        "/api/analyze",
        response_model=schemas.AnalyzeResponse,
        responses=schemas.error_responses(400, 413, 415),
        openapi_extra=request_body("/api/analyze"),
    )
    async def api_analyze(self, request: Request) -> Response:
        """Degree of freedom, dyadic solvability and, given positions, where it locks."""
        args = await read_route_args(request, "/api/analyze")
        try:
            found = await run_in_threadpool(analyze_mechanism, *args)
        except ValueError as exc:  # degenerate positions: named as /api/simulate names them
            raise ApiError(400, str(exc)) from None
        return await json_answer(found)

    @router.post(
        "/api/export",
        response_class=Response,
        responses={
            200: {
                "description": "the file, as an attachment",
                "content": {media: {} for media, _ in EXPORT_FORMATS.values()},
            },
            **schemas.error_responses(400, 413, 415),
            422: {"model": schemas.LockingResponse},
        },
        openapi_extra=request_body("/api/export"),
    )
    async def api_export(self, request: Request) -> Response:
        """The mechanism as an SVG, DXF or table file in millimetres, its crank `crank_mm`
        long (default 20), with the path of `path_joint` if given; 422 if that path locks,
        other 4xx JSON if it cannot."""
        args = await read_route_args(request, "/api/export")
        try:
            return await run_in_threadpool(export_file, *args)
        except LockingError as exc:  # only with a path: a locking mechanism has none
            return error_response(
                422, f"{exc}: it has no full path to draw", step=exc.step, node=exc.node
            )
        except ValueError as exc:  # the engine's message: the mechanism, the scale, path_joint
            raise ApiError(400, str(exc)) from None

    @router.post(
        "/api/kit",
        response_model=kit_schemas.KitResponse,
        responses={
            200: {
                "description": 'format "bom": the bill of materials; "glb", "zip": the file, '
                "as an attachment",
                "content": {media: {} for media, _ in KIT_FORMATS.values()},
            },
            422: {
                "model": schemas.ErrorResponse,
                "description": "no stacking of layers keeps every pin clear; or it locks "
                "(with step and node)",
            },
            **schemas.error_responses(400, 413, 415, 501, 503),
        },
        openapi_extra=request_body("/api/kit"),
    )
    async def api_kit(self, request: Request) -> Response:
        """The mechanism as printable parts in millimetres, its crank `crank_mm` long (default
        20): the bill of materials as JSON, the assembly as GLB or the whole build as a zip
        (`format`); 422 when no stacking of layers keeps every pin clear (or it locks), other
        4xx JSON for bad input, 503 with `Retry-After` when MAX_KITS are under way."""
        args = await read_route_args(request, "/api/kit")
        return await answer_kit(*args)

    @router.post(
        "/api/curve",
        response_model=schemas.CurveFileResponse,
        responses=schemas.error_responses(400, 413, 415, 422, 503),
        openapi_extra=request_body("/api/curve"),
    )
    async def api_curve(self, request: Request) -> Response:
        """The curve of a drawing's file sent as text (SVG, DXF, CSV or JSON, as `links
        synthesize --curve FILE#id` reads it): its points evenly spaced, and whether it is
        closed; 400 naming what is wrong with the file, 413 naming a limit on what it holds,
        422 when reading it overran a reader's time or memory, 503 when every reader is busy
        (`interop.curve_worker`)."""
        name, text, part = await read_route_args(request, "/api/curve")
        try:
            # In a reader process: no drawing can hold this replica's GIL, memory or time;
            # waiting for one takes none of the thread pool's tokens.
            curve = await self._admission.curves.read(name, text, part)
        except CurveReadersBusy as exc:
            raise ApiError(exc.status, str(exc), headers={"Retry-After": "1"}) from None
        except ValueError as exc:  # the file's problem, or the limit it passed, named
            raise ApiError(getattr(exc, "status", 400), str(exc)) from None
        return await json_answer({"points": curve.points, "closed": curve.closed})

    @router.post(
        "/api/retrieve",
        response_model=schemas.RetrieveResponse,
        responses=schemas.error_responses(400, 413, 415, 503),
        openapi_extra=request_body("/api/retrieve"),
    )
    async def api_retrieve(self, request: Request) -> Response:
        """The k curated paths nearest to a drawn curve, best first, with their mechanisms;
        503 with `Retry-After` when MAX_RETRIEVALS are already under way here."""
        args = await read_route_args(request, "/api/retrieve")
        points, k, min_transmission_deg, most = args
        # Claimed once the body is read and checked: a client that sends its body slowly, or
        # never, holds a connection until the body timeout, never a place of the index.
        self._admission.claim_retrieval()
        try:
            start = time.perf_counter()
            results = await self._backend.retrieve(points, k, min_transmission_deg, most)
            took_ms = (time.perf_counter() - start) * 1e3
        finally:
            self._admission.release_retrieval()
        # The results' numpy arrays become JSON lists only here, as the answer is rendered.
        return await json_answer({"results": results, "took_ms": round(took_ms, 3)})

    @router.post(
        "/api/synthesize",
        response_model=schemas.SynthesizeResponse,
        responses=schemas.error_responses(400, 413, 415, 503),
        openapi_extra=request_body("/api/synthesize"),
    )
    async def api_synthesize(self, request: Request) -> Response:
        """Mechanisms retrieved for a drawn curve and refined onto it, best first, within the
        request's `seconds` (or for its fixed `iterations`); 503 with `Retry-After` when
        MAX_SYNTHESES are under way here, when its retrieval would pass the retrieval limit,
        or when it would wait longer than its own budget. The budget starts when its
        refinement does (its retrieval counted), and `queued_ms` says how long it waited.
        With `"stream": true` the answer is NDJSON: a `{"progress": ...}` line each time the
        best so far improves, then the answer's own line (`serve.http.synthesis_run`). Counted work
        past MAX_SYNTHESIS_WORK is refused 400 before any; a synthesis whose client goes
        stops at its next refinement iteration (`serve.http.synthesis_run`)."""
        points, options, stream = await read_route_args(request, "/api/synthesize")
        seconds = options.seconds
        self._admission.claim_synthesis()  # once the body is read and checked, as a retrieval
        place: Place | None = None
        released = True  # until the refinement, once submitted, releases its place itself
        stop = threading.Event()  # set once the client has gone: the refinement stops
        try:
            start = time.perf_counter()
            wanted = retrievals(
                options.k, options.max_joints, options.front, options.min_transmission_deg
            )
            self._admission.claim_retrieval()  # counted as one retrieval: 503 beyond the limit
            try:
                retrieved, waited = await self._backend.retrieve_pooled(points, wanted)
            finally:
                self._admission.release_retrieval()
            retrieved_at = time.perf_counter()
            retrieval_s = retrieved_at - start - waited
            budget = None if seconds is None else max(0.0, seconds - retrieval_s)
            # Counted work is not weakened by waiting; it waits as long as a request may take.
            patience = (MAX_SYNTHESIS_SECONDS if seconds is None else seconds) - waited
            place = await self._admission.wait_for_refiner(budget, patience)
            reports: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
            place.began = time.perf_counter()
            refining = start_refinement(
                self._refining,
                points,
                retrieved,
                options,
                (retrieval_s, waited, retrieved_at),
                reports if stream else None,
                stop,
            )
            # The place is freed when the refinement ends, whether or not anyone still
            # reads its stream (a client gone mid-stream must not hold it for good).
            refining.add_done_callback(functools.partial(self._admission.release_synthesis, place))
            released = False
            if stream:
                return StreamingResponse(
                    synthesis_lines(reports, refining, start, request, stop),
                    media_type="application/x-ndjson",
                )
            results, queued_s = await unless_gone(request, refining, stop)
            took_ms = (time.perf_counter() - start) * 1e3
        finally:
            if released:
                self._admission.release_synthesis(place)
        return await json_answer(synthesis_answer(results, took_ms, queued_s))
