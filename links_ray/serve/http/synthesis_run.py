"""A synthesis request's refinement once its candidates are retrieved: run in the gateway's
refinement thread (`start_refinement`), answered whole (`unless_gone`, `synthesis_answer`) or
streamed as NDJSON lines (`synthesis_lines`), and stopped when its client goes.

The route (`serve.http.routes.LinksApiRoutes.api_synthesize`) reads the request, claims its place
and retrieves the candidates; what follows is here. A client's leaving is seen as its server's
`http.disconnect` (`client_gone`) or as Serve cancelling the route's wait; either sets the
refinement's `stop`, and it ends at its next iteration, freeing its place and the refiner.
Nothing here imports Ray.
"""

import asyncio
import threading
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from fastapi import Request

from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.pipeline import refine_retrieved
from links_ray.engine.synthesis.plan import RetrievalResult
from links_ray.engine.synthesis.results import SynthesisResults
from links_ray.serve.http.responses import json_line, logger

#: A synthesis whose client's server hands it one message after another, none of them the
#: client's leaving, looks again this often (uvicorn's waits for the next one).
GONE_POLL_S = 0.25


def start_refinement(
    refiner: ThreadPoolExecutor,
    points: np.ndarray,
    retrieved: list[RetrievalResult],
    options: SynthesisOptions,
    timing: tuple[float, float, float],
    reports: asyncio.Queue[dict[str, Any]] | None,
    stop: threading.Event,
) -> asyncio.Future[tuple[SynthesisResults, float]]:
    """The refinement of `retrieved` (their arrays as retrieved) onto `points`, submitted to
    `refiner`: its outcome is (results, seconds queued). `timing` is (seconds the retrieval
    took, seconds it waited for the index, `time.perf_counter()` when it ended): the budget
    counts the retrieval, never a wait. Each better best so far is put on `reports` (if
    given); `stop` ends it early."""
    retrieval_s, waited, retrieved_at = timing
    loop = asyncio.get_running_loop()
    progress = (
        None
        if reports is None
        else (lambda best: loop.call_soon_threadsafe(reports.put_nowait, best))
    )

    def refine() -> tuple[SynthesisResults, float]:
        began = time.perf_counter()
        results = refine_retrieved(
            points,
            retrieved,
            options,
            started=began - retrieval_s,  # waiting spent none of the budget
            progress=progress,
            stop=stop,
        )
        return results, waited + began - retrieved_at

    return loop.run_in_executor(refiner, refine)


async def client_gone(request: Request) -> None:
    """Return once the client of `request`, whose body is read, has gone (`http.disconnect`,
    or a connection its server can no longer read)."""
    try:
        while (await request.receive())["type"] != "http.disconnect":
            await asyncio.sleep(GONE_POLL_S)
    except (OSError, RuntimeError):
        return


async def unless_gone(
    request: Request,
    refining: asyncio.Future[tuple[SynthesisResults, float]],
    stop: threading.Event,
) -> tuple[SynthesisResults, float]:
    """`refining`'s outcome. If the client goes first, or this wait is cancelled (Serve
    cancels a request whose client has gone), `stop` is set: the refinement ends at its next
    iteration, and its place and the refiner are free for the next synthesis."""
    gone = asyncio.ensure_future(client_gone(request))
    try:
        await asyncio.wait({refining, gone}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:
        stop.set()
        raise
    finally:
        if gone.done() and not refining.done():
            stop.set()
        gone.cancel()
    return await refining


def synthesis_answer(results: SynthesisResults, took_ms: float, queued_s: float) -> dict[str, Any]:
    """A synthesis's answer: its results, the milliseconds it took and waited in them, and
    `unmet` when no candidate kept the constraints."""
    answer = {
        "results": list(results),
        "took_ms": round(took_ms, 3),
        "queued_ms": round(queued_s * 1e3, 3),
    }
    if results.unmet is not None:
        answer["unmet"] = results.unmet
    return answer


async def synthesis_lines(
    reports: asyncio.Queue[dict[str, Any]],
    refining: asyncio.Future[tuple[SynthesisResults, float]],
    start: float,
    request: Request,
    stop: threading.Event,
) -> AsyncIterator[bytes]:
    """A streamed synthesis: `{"progress": best so far}` lines while it refines, then
    `{"results", "took_ms", "queued_ms"}` (or `{"error"}` if it failed after the stream
    began). If the client goes, or the stream is closed, before the refinement ends, `stop`
    is set."""
    gone = asyncio.ensure_future(client_gone(request))
    try:
        while not refining.done() or not reports.empty():
            waiting = asyncio.ensure_future(reports.get())
            await asyncio.wait({waiting, refining, gone}, return_when=asyncio.FIRST_COMPLETED)
            if waiting.done():
                yield await json_line({"progress": waiting.result()})
            else:
                waiting.cancel()
            if gone.done():
                return
    finally:
        if not refining.done():
            stop.set()
        gone.cancel()
    try:
        results, queued_s = refining.result()
    except Exception as exc:  # the status is sent: the failure can only be a line
        logger.warning("links-ray API: a streamed synthesis failed (%s)", type(exc).__name__)
        yield await json_line({"error": "synthesis failed"})
        return
    took_ms = (time.perf_counter() - start) * 1e3
    yield await json_line(synthesis_answer(results, took_ms, queued_s))
