"""Checks of the buffers the compiled kernels are given: numba checks no bounds, so a short
buffer or an index past its end is refused here, by name, before a kernel runs.

Pure numpy: no numba, no Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.inputs import MIN_JOINTS, shown

__all__ = ["check_buffer", "check_indices", "check_packed_paths", "check_solution_path"]


def _shape_text(shape: tuple[int | None, ...]) -> str:
    """A shape as messages write it, None as "any"."""
    parts = ["any" if side is None else str(side) for side in shape]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def _an(text: str) -> str:
    """`text` after its article."""
    return (
        "an " if text.startswith(("int", "integer", "unsigned", "a", "e", "o")) else "a "
    ) + text


def check_buffer(
    name: str,
    array: object,
    shape: tuple[int | None, ...],
    dtype: type | str = np.float64,
    *,
    contiguous: bool = False,
    writeable: bool = False,
) -> None:
    """Refuse a buffer a compiled kernel would index past its end, or misread: unless `array`
    is a NumPy array of `shape` (None: any length on that axis) and `dtype` (a type, or kind
    characters such as "iu" for any integer), C-contiguous where `contiguous` and writeable
    where `writeable`, ValueError naming it, what was expected and what was given. numba
    checks no bounds: without this a short buffer is written past its end, silently.

    Costs about a microsecond; kernels called in loops by their own module, with buffers made
    there, are called without it."""
    if type(array) is np.ndarray:
        kind_ok = array.dtype.kind in dtype if isinstance(dtype, str) else array.dtype == dtype
        given = array.shape
        if (
            kind_ok
            and (not contiguous or array.flags.c_contiguous)
            and (not writeable or array.flags.writeable)
            and (
                given == shape
                or (
                    len(given) == len(shape)
                    and all(w is None or w == g for g, w in zip(given, shape, strict=True))
                )
            )
        ):
            return
    wanted_type = {"iu": "integer", "u": "unsigned integer", "f": "float"}.get(
        dtype, str(np.dtype(dtype)) if not isinstance(dtype, str) else f"kind {dtype!r}"
    )
    wanted = _an(
        f"{'writeable ' if writeable else ''}{'C-contiguous ' if contiguous else ''}"
        f"{wanted_type} array of shape {_shape_text(shape)}"
    )
    if not isinstance(array, np.ndarray):
        got = _an(type(array).__name__)
    else:
        layout = "" if array.flags.c_contiguous or not contiguous else "non-contiguous "
        frozen = "" if array.flags.writeable or not writeable else "read-only "
        got = _an(f"{frozen}{layout}{array.dtype} array of shape {_shape_text(array.shape)}")
    raise ValueError(f"{name} must be {wanted}, got {got}")


def check_indices(name: str, values: np.ndarray, limit: int, of: str) -> None:
    """Refuse indices a compiled kernel would follow out of bounds: unless every one of
    `values` lies in [0, limit), ValueError naming them and `of`, what they index."""
    if values.size and not (values.min() >= 0 and values.max() < limit):
        bad = values[(values < 0) | (values >= limit)].flat[0]
        raise ValueError(f"{name} must index {of} (0 to {limit - 1}), got {shown(bad)}")


def check_solution_path(
    order: object, joints: int, fixed: object = None, positions: str = "pos"
) -> None:
    """Refuse a solution path `order` (m, 3) of (joint, parent_a, parent_b) rows, or fixed
    joints `fixed` (f,), naming a joint outside the `joints` of the positions given with them
    (the buffer called `positions`), and positions without the crank's two joints."""
    if joints < MIN_JOINTS:
        raise ValueError(f"{positions} must hold at least the crank's 2 joints, got {joints}")
    of = f"the {joints} joints of {positions}"
    check_buffer("order", order, (None, 3), "iu")
    check_indices("order", order, joints, of)  # type: ignore[arg-type]
    if fixed is not None:
        check_buffer("fixed", fixed, (None,), "iu")
        check_indices("fixed", fixed, joints, of)  # type: ignore[arg-type]


def check_packed_paths(
    orders: np.ndarray,
    order_start: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
) -> None:
    """Refuse packed mechanisms (`search.mechanisms.MechanismBank`: solution paths `orders`
    (R, 3), `order_start` and `joint_start` (M + 1,)) and the (mechanisms[i], joints[i]) a
    kernel is to follow in them, naming the first bad buffer: a mechanism outside the M held,
    a joint outside its mechanism, or offsets that decrease."""
    check_buffer("orders", orders, (None, 3), "iu")
    check_buffer("order_start", order_start, (None,), "iu")
    count = order_start.shape[0] - 1
    check_buffer("joint_start", joint_start, (count + 1,), "iu")
    check_buffer("mechanisms", mechanisms, (None,), "iu")
    rows = mechanisms.shape[0]
    check_buffer("joints", joints, (rows,), "iu")
    if count < 0:
        raise ValueError("order_start must hold at least one entry, got none")
    check_indices("order_start", order_start, orders.shape[0] + 1, "the rows of orders")
    check_indices("mechanisms", mechanisms, count, f"the {count} mechanisms held")
    if rows:
        sizes = joint_start[mechanisms + 1] - joint_start[mechanisms]
        if (sizes < MIN_JOINTS).any() or (
            order_start[mechanisms + 1] < order_start[mechanisms]
        ).any():
            raise ValueError("order_start and joint_start must not decrease")
        if not ((joints >= 0) & (joints < sizes)).all():
            i = int(np.flatnonzero((joints < 0) | (joints >= sizes))[0])
            raise ValueError(
                f"joints must index each mechanism's joints: joints[{i}] = {int(joints[i])}, "
                f"mechanism {int(mechanisms[i])} has {int(sizes[i])}"
            )
