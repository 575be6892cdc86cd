"""Synthesis: mechanisms whose joint traces a drawn curve, retrieved and then refined
(`pipeline.synthesize`), within a budget (`budget`), under a designer's constraints
(`constraints`, `timing`), with coupler points added where an answer stalls
(`coupler_points`). Imports kinematics and fabrication (an answer's layer count as a kit).
"""

from links_ray.engine.synthesis.budget import IterationBudget, TimeBudget
from links_ray.engine.synthesis.constraints import Constraints
from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.pareto import pareto_front
from links_ray.engine.synthesis.pipeline import synthesize
from links_ray.engine.synthesis.refinement import Refinement, refine, refine_many

__all__ = [
    "Constraints",
    "IterationBudget",
    "Refinement",
    "SynthesisOptions",
    "TimeBudget",
    "pareto_front",
    "refine",
    "refine_many",
    "synthesize",
]
