"""Where an imported row came from: the ids `links import-release` gives the release's
mechanisms, and the way back (`release_location`).

    shard_id = SHARDS_PER_BATCH * release_batch + n_joints
    mechanism_id = BATCH_STRIDE * release_batch + release_index
    topology_id = mechanism_id // 5, variant = mechanism_id % 5   (the release's groups of 5)
    a negative's id = NEGATIVE_ID_BASE + mechanism_id

Pure numpy: no Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.data.generation import NEGATIVE_ID_BASE, VARIANTS

__all__ = ["BATCH_STRIDE", "SHARDS_PER_BATCH", "release_location"]

#: Ids a release batch spans: a multiple of 5, so a batch's groups of five stay topologies.
BATCH_STRIDE = VARIANTS * (1 << 22)
#: Shard ids a release batch spans: one per joint count.
SHARDS_PER_BATCH = 32


def release_location(mechanism_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(release_batch, release_index) of imported mechanism ids, valid or negative."""
    ids = np.asarray(mechanism_ids, dtype=np.int64)
    ids = np.where(ids >= NEGATIVE_ID_BASE, ids - NEGATIVE_ID_BASE, ids)
    return ids // BATCH_STRIDE, ids % BATCH_STRIDE
