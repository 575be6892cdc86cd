"""Refinement, synthesis's local search: a mechanism's joints moved so that one joint's path
traces a drawing, keeping it valid (`loop`), one guarded step (`step`, `step_kernels`), the
checks of a trial (`checks`), the solver with derivatives (`kernels`), and the entry points for
a caller's own arrays (`entry`).
"""

from links_ray.engine.synthesis.refinement.entry import refine, refine_many
from links_ray.engine.synthesis.refinement.loop import Refinement

__all__ = ["Refinement", "refine", "refine_many"]
