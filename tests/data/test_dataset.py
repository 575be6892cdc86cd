"""Reading the dataset: what a scan is given to hold."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from links_ray.data.dataset import value_set


def test_a_scan_filter_holds_its_values_in_arrow_memory() -> None:
    """A scan may drop its filter on an Arrow thread after `to_table` returns; values borrowed
    from NumPy then take the GIL there, and at interpreter exit that aborts the process
    (`isin`). Values in Arrow's memory pool are counted by `pa.total_allocated_bytes`; values
    borrowed from NumPy are not."""
    ids = np.array([7, 3, 7, 12, 3, 5], dtype=np.int64)
    before = pa.total_allocated_bytes()
    values = value_set(ids)
    assert sorted(values.to_pylist()) == [3, 5, 7, 12]
    assert pa.total_allocated_bytes() - before >= values.nbytes > 0
    assert sorted(value_set([4, 4, 1]).to_pylist()) == [1, 4]
