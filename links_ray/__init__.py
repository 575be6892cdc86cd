"""links-ray: the LINKS dataset of planar linkage mechanisms, generated and served on Ray.

`import links_ray` loads the engine (numpy/numba) and `load` (pyarrow), and nothing of Ray:
the package is built in layers (docs/design/architecture.md), held by tests/project/test_layers.py.
`ray_dataset` is the one name that needs Ray: it is loaded when first asked for.
"""

from links_ray.data.dataset import load
from links_ray.data.splits import SPLITS, split_of
from links_ray.engine.kinematics.mechanism import (
    InvalidMechanismError,
    LockingError,
    reduce_mechanism,
)
from links_ray.engine.kinematics.paths import chamfer, circle_variance, is_circle, normalize_path
from links_ray.engine.kinematics.sampling import PositionSampler, PositionSearch, sample_positions
from links_ray.engine.kinematics.solver import TopologySimulator, simulate, simulate_batch
from links_ray.engine.kinematics.topology import random_topology
from links_ray.engine.synthesis.pipeline import synthesize

__all__ = [
    "SPLITS",
    "InvalidMechanismError",
    "LockingError",
    "PositionSampler",
    "PositionSearch",
    "TopologySimulator",
    "chamfer",
    "circle_variance",
    "is_circle",
    "load",
    "normalize_path",
    "random_topology",
    "reduce_mechanism",
    "sample_positions",
    "simulate",
    "simulate_batch",
    "split_of",
    "synthesize",
]
__version__ = "0.4.0"


def __getattr__(name: str) -> object:
    if name == "ray_dataset":  # loads Ray, so only when asked for
        from links_ray.cluster.datasets import ray_dataset

        return ray_dataset
    raise AttributeError(f"module 'links_ray' has no attribute {name!r}")
