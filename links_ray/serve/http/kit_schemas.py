"""The answer of `POST /api/kit` with format "bom" as pydantic models: the kit's
`bom.json` (`engine.fabrication.kit.Kit.bom`), as `/openapi.json` shows it. Its request body is
`serve.http.schemas.KitRequest`, beside the others.
"""

from typing import Any, Literal

from pydantic import BaseModel, Field


class KitLink(BaseModel):
    """A link's bar: on `layer`, from z_mm[0] to z_mm[1]; its part lies along +x from its
    lower joint, placed there turned by `angle_deg` at the start."""

    joints: list[int]
    layer: int
    length_mm: float = Field(description="between its holes")
    kind: Literal["crank", "ground", "coupler"]
    z_mm: list[float]
    angle_deg: float
    node: str = Field(description="its node in assembly.glb")
    part: str = Field(description="its STL file in the kit")


class KitPin(BaseModel):
    """A joint's pin through its span of layers [lo, hi]; a post stands in the base plate."""

    joint: int
    layers: list[int]
    length_mm: float
    diameter_mm: float
    z_mm: list[float]
    post: bool
    node: str
    part: str


class KitSpacer(BaseModel):
    """A tube on a pin between its links on layers `between` (-1: the base plate)."""

    joint: int
    between: list[int]
    length_mm: float
    inner_diameter_mm: float
    outer_diameter_mm: float
    z_mm: list[float]
    node: str
    part: str


class KitBase(BaseModel):
    """The base plate the posts stand in: [min x, min y, max x, max y] and its heights."""

    extent_mm: list[float]
    z_mm: list[float]
    posts: list[int]
    hole_diameter_mm: float
    node: str
    part: str


class KitResponse(BaseModel):
    """200 from /api/kit with format "bom": the kit's bom.json, in mm, z up; a
    position p of the mechanism is at (p - origin) * mm_per_unit."""

    unit: Literal["mm"]
    frame: Literal["crank", "drawing"]
    crank_mm: float
    mm_per_unit: float
    origin: list[float]
    layers: int
    lower_bound: int = Field(description="the fewest layers any plan could use")
    optimal: bool
    status: Literal["optimal", "work limit", "time limit", "heuristic"]
    bar_width_mm: float
    hole_diameter_mm: float
    pin_diameter_mm: float
    spacer_diameter_mm: float
    clearance_mm: float
    layer_thickness_mm: float
    layer_gap_mm: float
    ground_on_base: bool
    links: list[KitLink]
    pins: list[KitPin]
    spacers: list[KitSpacer]
    base: KitBase | None
    joints: list[dict[str, Any]] = Field(description="joint, type, x_mm, y_mm at the start")
    parts: list[str] = Field(description="the STL files of the kit: each part once")
    assembly: str
    took_ms: float
