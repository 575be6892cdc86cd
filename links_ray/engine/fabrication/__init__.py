"""Fabrication: a mechanism in millimetres (`drawings`), which of its bars come too close over
the turn (`collisions`), each link on a layer (`layers`, `layer_search`), and the kit of parts
to print (`kit`), with their limits (`limits`). Imports kinematics, never synthesis.
"""

from links_ray.engine.fabrication.collisions import Collisions, find_collisions
from links_ray.engine.fabrication.drawings import Fabrication, fabrication
from links_ray.engine.fabrication.kit import Kit, KitOptions, plan_kit
from links_ray.engine.fabrication.layers import LayeringError, LayerPlan, plan_layers

__all__ = [
    "Collisions",
    "Fabrication",
    "Kit",
    "KitOptions",
    "LayerPlan",
    "LayeringError",
    "fabrication",
    "find_collisions",
    "plan_kit",
    "plan_layers",
]
