"""links-ray: the LINKS dataset of planar linkage mechanisms, generated and served on Ray."""

from links_ray.mechanism import InvalidMechanismError, LockingError
from links_ray.solver import TopologySimulator, simulate, simulate_batch

__all__ = [
    "InvalidMechanismError",
    "LockingError",
    "TopologySimulator",
    "simulate",
    "simulate_batch",
]
__version__ = "0.1.0"
