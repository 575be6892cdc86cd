"""Kinematics: mechanisms and their topologies, the compiled dyadic solver and its check
between sampled steps, coupler paths and their normalization, valid initial positions,
transmission angles, and a plain-Python reference solver. Imports no other room of the engine.
"""

from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.mechanism import LockingError, Topology, reduce_mechanism
from links_ray.engine.kinematics.paths import chamfer, circle_variance, is_circle, normalize_path
from links_ray.engine.kinematics.reference import simulate_reference
from links_ray.engine.kinematics.sampling import PositionSampler, PositionSearch, sample_positions
from links_ray.engine.kinematics.solver import TopologySimulator, simulate, simulate_batch
from links_ray.engine.kinematics.topology import random_topology

__all__ = [
    "InvalidMechanismError",
    "LockingError",
    "PositionSampler",
    "PositionSearch",
    "Topology",
    "TopologySimulator",
    "chamfer",
    "circle_variance",
    "is_circle",
    "normalize_path",
    "random_topology",
    "reduce_mechanism",
    "sample_positions",
    "simulate",
    "simulate_batch",
    "simulate_reference",
]
