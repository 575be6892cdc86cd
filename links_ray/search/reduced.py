"""How many joints each path's reduced mechanism has
(`engine.kinematics.mechanism.reduce_mechanism`: the path's joint and every joint its motion depends
on, fixed joints included), from the packed solution paths of a `MechanismBank`, so that retrieval
can keep only simple mechanisms without saving anything more per path.

A solution path lists every joint after the joints it is solved from, so one pass over it
backwards, from the path's joint, marks every joint that joint needs; the crank's joint 1
needs joint 0. Pure numpy/numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer, check_indices, check_packed_paths


@njit(cache=True, nogil=True)
def _reduced_joints(
    orders: np.ndarray,
    order_start: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[i] = the joints of the reduced mechanism of joint joints[i] of mechanism
    mechanisms[i]."""
    largest = 0
    for m in range(joint_start.shape[0] - 1):
        largest = max(largest, joint_start[m + 1] - joint_start[m])
    needed = np.zeros(largest, dtype=np.bool_)
    for i in range(mechanisms.shape[0]):
        m = mechanisms[i]
        n = joint_start[m + 1] - joint_start[m]
        needed[:n] = False
        needed[joints[i]] = True
        for row in range(order_start[m + 1] - 1, order_start[m] - 1, -1):
            if needed[orders[row, 0]]:
                needed[orders[row, 1]] = True
                needed[orders[row, 2]] = True
        if needed[1]:
            needed[0] = True
        count = 0
        for j in range(n):
            count += needed[j]
        out[i] = count


def reduced_joints(
    orders: np.ndarray,
    order_start: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
    out: np.ndarray,
) -> None:
    """out (F,) int16: the joints of the reduced mechanism of joint joints[i] of mechanism
    mechanisms[i], of mechanisms packed as a `MechanismBank` packs them (`orders` (R, 3),
    `order_start` and `joint_start` (M + 1,))."""
    check_packed_paths(orders, order_start, joint_start, mechanisms, joints)
    check_buffer("out", out, (mechanisms.shape[0],), np.int16)
    largest = int(np.diff(joint_start).max()) if len(joint_start) > 1 else 0
    check_indices("orders", orders, largest, "the joints of the largest mechanism")
    _reduced_joints(orders, order_start, joint_start, mechanisms, joints, out)
