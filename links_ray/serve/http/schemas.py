"""The HTTP API's request and response bodies as pydantic models: what `/openapi.json` shows.

Every bound comes from the limit the body's check enforces (`links_ray.engine.inputs`, the
synthesis options and constraints, fabrication's limits, `serve.http.limits`), defined once. The
routes read and check a body with the engine's own validators (`serve.http.bodies.CONVERTERS`),
so a refused request names its problem in the engine's words, and 10,000 drawn points are
checked by NumPy, not field by field; the models are the schema those checks enforce
(tests/serve/test_bodies_agree.py holds each model to its converter, bound by bound), and the
shapes the routes answer with.
"""

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from links_ray.engine.fabrication.kit import (
    DEFAULT_BAR_WIDTH_MM,
    DEFAULT_CLEARANCE_MM,
    DEFAULT_HOLE_DIAMETER_MM,
    DEFAULT_LAYER_GAP_MM,
    DEFAULT_LAYER_THICKNESS_MM,
    DEFAULT_PIN_DIAMETER_MM,
    DEFAULT_SPACER_DIAMETER_MM,
)
from links_ray.engine.fabrication.limits import DEFAULT_CRANK_MM, MAX_CRANK_MM, MAX_DRAWING_MM
from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_STEPS,
    MAX_COORDINATE,
    MAX_DATASET_JOINTS,
    MAX_K,
    MAX_POINTS,
    MAX_STEPS,
    MAX_TRANSMISSION_DEG,
    MIN_JOINTS,
    MIN_K,
    MIN_POINTS,
    MIN_STEPS,
)
from links_ray.engine.node_kinds import ACTUATED, FIXED
from links_ray.engine.synthesis.candidates import UnrefinedWhy
from links_ray.engine.synthesis.constraints import MAX_LAYERS, MAX_LINK_RATIO
from links_ray.engine.synthesis.options import (
    DEFAULT_SYNTHESIS_SECONDS,
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    MAX_SEED,
    MAX_SYNTHESIS_ITERATIONS,
    MAX_SYNTHESIS_SECONDS,
    MAX_TIMING_DEG,
)
from links_ray.serve.http.limits import MAX_CURVE_NAME_CHARS, MAX_KIT_JOINTS, MAX_REQUEST_JOINTS

Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
#: [x, y]
Point = Annotated[list[Coordinate], Field(min_length=2, max_length=2)]
Joints = Field(min_length=MIN_JOINTS, max_length=MAX_REQUEST_JOINTS)
#: An adjacency entry, and a joint's kind (`engine.node_kinds`): integers in a range rather than
#: Literals, which would take true for 1 as Python does; JSON's booleans are no numbers here.
Link = Annotated[int, Field(ge=0, le=1)]
Kind = Annotated[int, Field(ge=FIXED, le=ACTUATED)]
#: A crank angle of `timing`, degrees.
Angle = Annotated[float, Field(ge=-MAX_TIMING_DEG, le=MAX_TIMING_DEG)]


class Request(BaseModel):
    """A request body: a JSON object; a field it does not name is refused (400). Strict, as
    the routes read JSON: no text for a number, no boolean for an integer. A field whose
    schema allows null takes it for its default."""

    model_config = ConfigDict(extra="forbid", strict=True)


class Mechanism(BaseModel):
    """docs/reference/contract.md, Mechanisms: joint 0 fixed, joint 1 the crank's tip."""

    adjacency: Annotated[list[list[Link]], Joints] = Field(
        description="n x n, symmetric, zero diagonal: 1 where two joints are linked"
    )
    node_types: Annotated[list[Kind], Joints] = Field(
        description="per joint: 0 fixed, 1 simple, 2 actuated (joint 1 only)"
    )
    positions: Annotated[list[Point], Joints] = Field(description="initial [x, y] per joint")


class SimulateRequest(Request, Mechanism):
    """POST /api/simulate. Joints x steps is at most `max_joint_steps` (GET /api/limits)."""

    steps: int | None = Field(DEFAULT_STEPS, ge=MIN_STEPS, le=MAX_STEPS, description="crank steps")


class AnalyzeRequest(Request):
    """POST /api/analyze: a topology, and optionally positions to simulate."""

    adjacency: Annotated[list[list[Link]], Joints]
    node_types: Annotated[list[Kind], Joints]
    positions: Annotated[list[Point], Joints] | None = None
    steps: int | None = Field(DEFAULT_STEPS, ge=MIN_STEPS, le=MAX_STEPS)


class CurveRequest(Request):
    """A drawn curve, not all one point, and the answers wanted for it."""

    points: Annotated[list[Point], Field(min_length=MIN_POINTS, max_length=MAX_POINTS)]
    k: int | None = Field(DEFAULT_K, ge=MIN_K, le=MAX_K, description="results wanted")
    min_transmission: float | None = Field(
        0.0,
        ge=0.0,
        le=MAX_TRANSMISSION_DEG,
        description="only mechanisms whose least transmission angle is at least this, degrees",
    )


MaxJoints = Field(
    None,
    ge=MIN_JOINTS,
    le=MAX_DATASET_JOINTS,
    description="only paths whose reduced mechanism has at most this many joints",
)
#: [xmin, ymin, xmax, ymax], in the drawing's units and frame
Box = Annotated[list[Coordinate], Field(min_length=4, max_length=4)]


class RetrieveRequest(CurveRequest):
    """POST /api/retrieve: a drawn curve, not all one point."""

    max_joints: int | None = MaxJoints


class DesignConstraints(Request):
    """What every synthesis result keeps, in the drawing's own units and frame."""

    pivots: Box | None = Field(None, description="every fixed joint inside this box")
    footprint: Box | None = Field(
        None, description="every joint inside this box through the whole crank turn"
    )
    max_link_ratio: float | None = Field(
        None,
        ge=1.0,
        le=MAX_LINK_RATIO,
        description="the longest link at most this many times the shortest",
    )
    min_link: float | None = Field(
        None, gt=0.0, le=MAX_COORDINATE, description="every link at least this long"
    )
    max_link: float | None = Field(
        None, gt=0.0, le=MAX_COORDINATE, description="every link at most this long"
    )
    max_layers: int | None = Field(
        None,
        ge=1,
        le=MAX_LAYERS,
        description=(
            "at most this many layers as a kit at the default sizes scaled to its crank (bars "
            "0.4 of the crank wide), checked at the answer"
        ),
    )


class SynthesizeRequest(CurveRequest):
    """POST /api/synthesize: retrieval, then refinement within `seconds`, or for a fixed
    number of `iterations`."""

    seconds: float | None = Field(
        DEFAULT_SYNTHESIS_SECONDS,
        gt=0.0,
        le=MAX_SYNTHESIS_SECONDS,
        description="time budget (not with iterations); it starts when the refinement does",
    )
    iterations: int | None = Field(
        None,
        ge=1,
        le=MAX_SYNTHESIS_ITERATIONS,
        description="counted work instead of a time budget: equal requests, bit-equal answers",
    )
    min_transmission: float | None = Field(
        DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
        ge=0.0,
        le=MAX_TRANSMISSION_DEG,
        description="the least transmission angle kept, degrees (0: refinement's own margin)",
    )
    seed: int | None = Field(0, ge=0, le=MAX_SEED, description="seed of the random restarts")
    partial: bool = Field(False, description="the drawing is part of a curve: match a run")
    max_joints: int | None = MaxJoints
    front: bool = Field(
        False,
        description=(
            "answer the best result of each joint count that beats every simpler one, by "
            "joints ascending, instead of the k best"
        ),
    )
    constraints: DesignConstraints | None = Field(
        None, description="kept by every result; `unmet` in the answer when none can"
    )
    timing: bool | list[Angle] | None = Field(
        None,
        description=(
            "true: the points are reached at equal crank steps over a turn, in order, from a "
            "free start; or each point's crank angle in degrees (relative to a free start)"
        ),
    )
    stream: bool = Field(
        False,
        description=(
            "answer in NDJSON: a {progress} line (the best so far, with every joint's "
            "trajectories and elapsed_ms) each time it improves, then {results, took_ms}"
        ),
    )


class CurveFileRequest(Request):
    """POST /api/curve: a drawing's file, its curve read as `links synthesize --curve` reads
    it (SVG, DXF, CSV or JSON; the body at most `max_body_bytes`)."""

    name: str = Field(
        min_length=1,
        max_length=MAX_CURVE_NAME_CHARS,
        description="the file's name: its extension (.svg, .dxf, .csv, .json) says how to read it",
    )
    text: str = Field(description="the file's contents")
    id: str | None = Field(
        None,
        min_length=1,
        max_length=MAX_CURVE_NAME_CHARS,
        description="an SVG element's id or a DXF layer's name (FILE#id); else the first curve",
    )


class CurveFileResponse(BaseModel):
    """200 from /api/curve: the curve sampled evenly by arc length, in the drawing's units
    (an SVG's y negated, so that it reads as drawn)."""

    points: list[Point]
    closed: bool = Field(description="a closed curve: its last point does not repeat its first")


class ErrorResponse(BaseModel):
    """Every refusal: 4xx (or 503 with Retry-After when busy) and what is wrong."""

    error: str


class LockingResponse(BaseModel):
    """422 from /api/simulate: the mechanism cannot be assembled at `step`, joint `node`."""

    error: Literal["locking"]
    step: int
    node: int


class PartitionInfo(BaseModel):
    """One partition of a split index, and the curated paths it holds."""

    part: int
    paths: int


class HealthResponse(BaseModel):
    """GET /api/health; `shards` (its partitions; the field's name is the API's) when the
    index is split into partitions."""

    status: Literal["ok"]
    paths: int = Field(description="curated paths indexed")
    shards: list[PartitionInfo] | None = Field(
        default=None, description="the index's partitions, when it is split (--shards N)"
    )


class LimitsResponse(BaseModel):
    """GET /api/limits: `serve.http.limits.request_limits()`."""

    min_points: int
    max_points: int
    min_k: int
    max_k: int
    default_k: int
    min_joints: int
    max_joints: int
    min_steps: int
    max_steps: int
    default_steps: int
    max_joint_steps: int
    max_seconds: float
    max_iterations: int
    max_synthesis_work: int
    max_kit_joints: int
    default_seconds: float
    max_transmission_deg: float
    max_coordinate: float
    max_body_bytes: int
    body_timeout_s: float
    min_body_bytes_per_s: int
    max_url_bytes: int
    max_head_bytes: int
    max_headers: int
    head_timeout_s: float


class SimulateResponse(BaseModel):
    """200 from /api/simulate: every joint's position at every crank step."""

    trajectories: list[list[Point]] = Field(description="[joint][step] = [x, y]")


class RetrieveResult(BaseModel):
    """A curated path near the query, and its mechanism placed in the query's frame."""

    path_id: int
    mechanism_id: int
    joint: int = Field(description="the path's joint in the stored mechanism")
    chamfer: float = Field(description="between the normalized query and path")
    min_transmission_deg: float | None = None
    n_joints: int = Field(description="joints of `mechanism`, the path's reduced mechanism")
    points: list[Point] = Field(description="the path, normalized")
    mechanism: Mechanism = Field(description="reduced to the joints the path needs")
    mechanism_joint: int = Field(description="the path's joint in `mechanism`")


class RetrieveResponse(BaseModel):
    """200 from /api/retrieve: the nearest curated paths, and the milliseconds it took."""

    results: list[RetrieveResult] = Field(description="best first")
    took_ms: float


class Interval(BaseModel):
    """The run of crank steps a partial curve matches."""

    start_step: int
    steps: int
    start_deg: float
    sweep_deg: float


class SynthesisResult(BaseModel):
    """A retrieved mechanism refined onto the drawing."""

    path_id: int
    mechanism_id: int
    chamfer: float = Field(description="in the drawing's frame, over its longest chord")
    retrieved_chamfer: float
    mechanism: Mechanism
    mechanism_joint: int
    path: list[Point] = Field(description="the joint's path, in the drawing's frame")
    interval: Interval | None = None
    n_joints: int = Field(description="joints of `mechanism` (reduced to what the path needs)")
    n_links: int = Field(description="links of `mechanism`, the crank included")
    coupler_points: int = Field(
        0,
        description=(
            "joints the polish added to the stored mechanism (the last traces); 0 when "
            "`mechanism` is the stored one, moved"
        ),
    )
    timed_error: float | None = Field(
        None,
        description="with timing: mean distance of each point from the path at its crank angle, "
        "over the drawing's longest chord",
    )
    layers: int | None = Field(
        None,
        description=(
            "with front or max_layers: its layers as a kit at the default sizes scaled to its "
            "crank; null when no stacking exists (absent otherwise)"
        ),
    )
    refined: bool = Field(description="refinement kept a step of it; false: as retrieved")
    why: UnrefinedWhy | None = Field(description="null if refined, else why not (contract.md)")


class Unmet(BaseModel):
    """The constraint the nearest candidate misses most, and by how much in its own units."""

    constraint: Literal[
        "pivots",
        "footprint",
        "max_link_ratio",
        "min_link",
        "max_link",
        "max_layers",
        "min_transmission",
    ]
    by: float


class SynthesizeResponse(BaseModel):
    """200 from /api/synthesize: refined mechanisms, and the milliseconds it took and waited."""

    results: list[SynthesisResult] = Field(
        description="best first; with `front`, by joints ascending; [] with `unmet`"
    )
    took_ms: float
    queued_ms: float = Field(description="of took_ms, waited behind other work")
    unmet: Unmet | None = Field(
        None, description="when constraints were given and no candidate could keep them"
    )


class Lock(BaseModel):
    """Where a mechanism locks: the crank step, the joint that cannot be placed, the angle."""

    step: int
    node: int
    angle: float = Field(description="the crank's turn at the lock, degrees")


class AnalyzeResponse(BaseModel):
    """The studio's analysis: mobility, solvability, dataset rules, where it locks."""

    joints: int
    moving: int
    links: int
    dof: int
    solvable: bool
    problem: str | None
    order: list[list[int]] = Field(description="solution path rows [joint, parent_a, parent_b]")
    lock: Lock | None
    dataset_rules: list[str] | None = None
    trajectories: list[list[Point]] | None = Field(None, description="the steps before a lock")


class ExportRequest(Request, Mechanism):
    """POST /api/export: the mechanism drawn in millimetres, answered as a file."""

    format: Literal["svg", "dxf", "table"] = Field("svg", description="the file's format")
    crank_mm: float | None = Field(
        DEFAULT_CRANK_MM, gt=0, le=MAX_CRANK_MM, description="the crank's length in mm"
    )
    path_joint: int | None = Field(None, ge=0, description="a moving joint whose path is drawn too")


#: A kit's joints: at most MAX_KIT_JOINTS, fewer than any other mechanism of a request.
KitJoints = Field(min_length=MIN_JOINTS, max_length=MAX_KIT_JOINTS)


class KitRequest(Request, Mechanism):
    """POST /api/kit: the mechanism as printable parts, in millimetres (engine.fabrication.kit;
    docs/guides/building.md): the pin narrower than the hole, the hole than the spacer, the
    spacer than the bar."""

    adjacency: Annotated[list[list[Link]], KitJoints] = Field(
        description="n x n, symmetric, zero diagonal: 1 where two joints are linked"
    )
    node_types: Annotated[list[Kind], KitJoints] = Field(
        description="per joint: 0 fixed, 1 simple, 2 actuated (joint 1 only)"
    )
    positions: Annotated[list[Point], KitJoints] = Field(description="initial [x, y] per joint")
    format: Literal["bom", "glb", "zip"] = Field(
        "bom", description="bom: the bill as JSON; glb: the assembly; zip: the whole kit"
    )
    crank_mm: float | None = Field(
        DEFAULT_CRANK_MM, gt=0, le=MAX_CRANK_MM, description="the crank's length in mm"
    )
    bar_width_mm: float | None = Field(DEFAULT_BAR_WIDTH_MM, gt=0, le=MAX_DRAWING_MM)
    hole_diameter_mm: float | None = Field(DEFAULT_HOLE_DIAMETER_MM, gt=0, le=MAX_DRAWING_MM)
    pin_diameter_mm: float | None = Field(DEFAULT_PIN_DIAMETER_MM, gt=0, le=MAX_DRAWING_MM)
    spacer_diameter_mm: float | None = Field(
        DEFAULT_SPACER_DIAMETER_MM,
        gt=0,
        le=MAX_DRAWING_MM,
        description="the spacers' outside: the pins' width in the layer plan",
    )
    clearance_mm: float | None = Field(
        DEFAULT_CLEARANCE_MM,
        ge=0,
        le=MAX_DRAWING_MM,
        description="the least gap between parts on one layer over the whole turn",
    )
    layer_thickness_mm: float | None = Field(DEFAULT_LAYER_THICKNESS_MM, gt=0, le=MAX_DRAWING_MM)
    layer_gap_mm: float | None = Field(
        DEFAULT_LAYER_GAP_MM, ge=0, le=MAX_DRAWING_MM, description="kept by washers"
    )
    ground_on_base: bool | None = Field(False, description="fixed pins stand on a base plate")


def error_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries: ErrorResponse for each status."""
    return {status: {"model": ErrorResponse} for status in statuses}


#: The request body model of each POST route.
REQUEST_MODELS: dict[str, type[BaseModel]] = {
    "/api/simulate": SimulateRequest,
    "/api/analyze": AnalyzeRequest,
    "/api/retrieve": RetrieveRequest,
    "/api/synthesize": SynthesizeRequest,
    "/api/export": ExportRequest,
    "/api/curve": CurveFileRequest,
    "/api/kit": KitRequest,
}


def request_body(path: str) -> dict[str, Any]:
    """The OpenAPI `requestBody` of a POST route (its `openapi_extra`): its model in
    `REQUEST_MODELS`. The routes read their bodies themselves (`serve.http.bodies`: size, media
    type, the engine's checks), so FastAPI does not see the model; `serve.http.openapi` adds its
    schema to the document."""
    name = REQUEST_MODELS[path].__name__
    schema = {"$ref": f"#/components/schemas/{name}"}
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": schema}}}}
