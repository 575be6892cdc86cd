"""Retrieval results compared as values: `==` between dicts that hold numpy arrays is
ambiguous (it asks an array for one truth value), so `differences` compares arrays by type,
dtype, shape and every number, and everything else with `==`."""

from __future__ import annotations

from typing import Any

import numpy as np


def differences(got: Any, expected: Any, where: str = "") -> list[str]:
    """Where `got` and `expected` differ (empty if they hold the same values, arrays of the
    same dtype and shape among them); each place named by its keys and indices."""
    if isinstance(got, np.ndarray) or isinstance(expected, np.ndarray):
        same = (
            isinstance(got, np.ndarray)
            and isinstance(expected, np.ndarray)
            and got.dtype == expected.dtype
            and got.shape == expected.shape
            and np.array_equal(got, expected)
        )
        return [] if same else [f"{where or 'value'}: {got!r} != {expected!r}"]
    if isinstance(got, dict) and isinstance(expected, dict):
        if list(got) != list(expected):
            return [f"{where or 'value'}: keys {list(got)} != {list(expected)}"]
        return [d for key in got for d in differences(got[key], expected[key], f"{where}[{key!r}]")]
    if isinstance(got, list) and isinstance(expected, list):
        if len(got) != len(expected):
            return [f"{where or 'value'}: {len(got)} items != {len(expected)}"]
        return [
            d
            for i, (a, b) in enumerate(zip(got, expected, strict=True))
            for d in differences(a, b, f"{where}[{i}]")
        ]
    same = type(got) is type(expected) and got == expected
    return [] if same else [f"{where or 'value'}: {got!r} != {expected!r}"]


def assert_same_results(got: Any, expected: Any) -> None:
    """Assert that two answers (result dicts, lists of them, or anything holding arrays) hold
    the same values, naming the first few places they differ."""
    found = differences(got, expected)
    assert not found, "; ".join(found[:5])
