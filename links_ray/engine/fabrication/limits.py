"""Limits of fabrication: the sizes of exported drawings, and of mechanisms built as bars in
layers, with the checks that enforce them.

Shared limits (mechanisms, coordinates, numbers in a range) are in `engine.inputs`.
"""

from __future__ import annotations

from links_ray.engine.inputs import MAX_COORDINATE, as_real, positive_at_most

# -- fabrication drawings (engine.fabrication.drawings) --------------------------------------------

#: The crank length of an exported drawing, in millimetres, by default and at most (100 m).
DEFAULT_CRANK_MM, MAX_CRANK_MM = 20.0, 1e5
#: The most an exported drawing may span, in millimetres (1 km): a crank much shorter than the
#: other links would otherwise blow a drawing up past what any CAD program lays out.
MAX_DRAWING_MM = 1e6


# -- layered builds (engine.fabrication.collisions, engine.fabrication.layers) ---------------------

#: Largest mechanism a layered build takes, in joints: every pair of its links is checked over
#: the turn, and the pairs grow as the square of the joints.
MAX_LAYERED_JOINTS = 100
#: Crank steps at which a layered build's pairs are first measured; the check between the steps
#: (engine.fabrication.collisions) proves the rest of the turn.
DEFAULT_COLLISION_STEPS = 360


def as_crank_mm(value: object, name: str = "crank_mm") -> float:
    """A crank length in millimetres: more than 0 and at most MAX_CRANK_MM, or ValueError
    naming the option `name`."""
    return positive_at_most(value, name, MAX_CRANK_MM, "a number of millimetres", " mm")


def as_bar_sizes(
    bar_width: object, clearance: object, pin_diameter: object
) -> tuple[float, float, float]:
    """A layered build's (bar_width, clearance, pin_diameter), lengths in the unit of the
    positions: the width and the diameter more than 0, the clearance 0 or more, each at most
    MAX_COORDINATE, and the pin narrower than the bar (its hole must leave the bar whole);
    else ValueError naming the problem."""
    bar_width = positive_at_most(bar_width, "bar_width", MAX_COORDINATE, "a length", "")
    pin_diameter = positive_at_most(pin_diameter, "pin_diameter", MAX_COORDINATE, "a length", "")
    clearance = as_real("clearance", clearance, "a length")
    if not 0.0 <= clearance <= MAX_COORDINATE:  # written so that NaN fails too
        raise ValueError(f"clearance must be from 0 to {MAX_COORDINATE:g}, got {clearance:g}")
    if not pin_diameter < bar_width:
        raise ValueError(
            f"pin_diameter must be less than bar_width (a pin's hole must leave its bar whole), "
            f"got {pin_diameter:g} and {bar_width:g}"
        )
    return bar_width, clearance, pin_diameter
