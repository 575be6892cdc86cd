"""`POST /api/kit`'s work: a mechanism planned as a kit of printable parts
(`engine.fabrication.kit`) and made (`interop.parts`), answered as its bill of materials, its
assembly's glTF binary or a zip of the whole kit.

Making a kit holds a core for its layer plan's counted work (`engine.fabrication.layers`; bounded
behind it by `PLAN_SECONDS`) and its parts' making, so a replica makes one at a time, in a thread of
its own below the event loop (`admission.low_priority_thread`), and holds at most `MAX_KITS`, made
or waiting: one more is answered 503 with `Retry-After` at once. The mechanism is at most
`MAX_REQUEST_JOINTS` joints (413), and a kit at most `MAX_KIT_JOINTS` (400, by `bodies.kit_args`,
before it takes a place), which bounds the checks and the parts, so the time and the memory of
making a kit. A place is freed when its kit is made, whether or not its client still waits.
Nothing here imports Ray.
"""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor

from fastapi.responses import Response

from links_ray.engine.fabrication.kit import Kit, KitOptions, plan_kit
from links_ray.engine.fabrication.layers import LayeringError
from links_ray.engine.kinematics.mechanism import LockingError
from links_ray.serve.http.admission import busy, low_priority_thread
from links_ray.serve.http.bodies import KIT_FORMATS
from links_ray.serve.http.limits import MAX_KITS
from links_ray.serve.http.responses import ApiError, error_response, json_answer

__all__ = ["LINE", "MAX_KITS", "KitLine", "answer_kit", "make"]


class KitLine:
    """A replica's kits: how many it holds, and the one thread that makes them."""

    def __init__(self) -> None:
        self.held = 0
        self._thread: ThreadPoolExecutor | None = None

    @property
    def thread(self) -> ThreadPoolExecutor:
        """The kit thread, started when first needed (the docs' hook imports this module and
        makes no kit)."""
        if self._thread is None:
            self._thread = low_priority_thread("links-kit")
        return self._thread

    def claim(self) -> None:
        """A place for one kit, or 503 with `Retry-After` when MAX_KITS are held."""
        if self.held >= MAX_KITS:
            raise busy(f"{MAX_KITS} kits are being made here: try again shortly")
        self.held += 1

    def release(self) -> None:
        """Free a kit's place."""
        self.held -= 1


#: This replica's kits (a replica is one process, and its event loop one thread).
LINE = KitLine()


def make(
    adjacency: list, node_types: list, positions: list, options: KitOptions, chosen: str
) -> tuple[Kit, bytes | None]:
    """The planned kit and, for "glb" and "zip", the file (`interop.parts`)."""
    from links_ray.interop.parts import assembly_glb, kit_files, kit_zip, part_meshes

    kit = plan_kit(adjacency, node_types, positions, options)
    if chosen == "glb":
        return kit, assembly_glb(kit, part_meshes(kit))
    if chosen == "zip":
        return kit, kit_zip(kit_files(kit))
    return kit, None


async def answer_kit(
    adjacency: list, node_types: list, positions: list, options: KitOptions, chosen: str
) -> Response:
    """The kit of `/api/kit` (its body read by `bodies.kit_args`, which refuses a mechanism of
    more than MAX_KIT_JOINTS joints), made in the kit thread; ApiError naming why not: 400 for
    the engine's refusals, 422 when no stacking of layers keeps every pin clear or the
    mechanism locks, 501 without the 3D libraries, 503 when busy."""
    LINE.claim()
    start = time.perf_counter()
    loop = asyncio.get_running_loop()
    try:
        work = LINE.thread.submit(make, adjacency, node_types, positions, options, chosen)
    except BaseException:
        LINE.release()
        raise
    # Freed when the thread is done with it, on the event loop's thread: a client that leaves
    # cancels only its wait, and the kit still holds its place until it is made.
    work.add_done_callback(lambda _: loop.call_soon_threadsafe(LINE.release))
    try:
        kit, data = await asyncio.wrap_future(work)
    except LockingError as exc:
        return error_response(
            422, f"{exc}: it has no full turn to build", step=exc.step, node=exc.node
        )
    except LayeringError as exc:
        raise ApiError(422, str(exc)) from None
    except ValueError as exc:  # the engine's message: the mechanism, a size, a short link
        raise ApiError(400, str(exc)) from None
    except ImportError as exc:  # the `build` extra is not installed on this server
        raise ApiError(501, str(exc)) from None
    took_ms = round((time.perf_counter() - start) * 1e3, 3)
    if data is None:
        return await json_answer({**kit.bom(), "took_ms": took_ms})
    media_type, suffix = KIT_FORMATS[chosen]
    what = "assembly" if chosen == "glb" else "kit"
    name = f"mechanism-{len(node_types)}-joints-{what}.{suffix}"
    return Response(
        data,
        media_type=media_type,
        headers={
            "Content-Disposition": f'attachment; filename="{name}"',
            "X-Content-Type-Options": "nosniff",
            "X-Took-Ms": str(took_ms),
        },
    )
