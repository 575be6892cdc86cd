"""The data the service benchmarks share: a cached dataset of curated paths
(`retrieval_dataset`, for `links bench retrieve`, `serve` and `synthesize`) and the bytes a
folder holds on disk."""

from __future__ import annotations

import os
import shutil

#: Curated paths a mechanism gives with the default topology rules, a little under what they
#: give on average, so that the first dataset made is rarely too small.
CURATED_PER_MECHANISM = 4.2


def retrieval_dataset(paths: int, folder: str | None = None) -> str:
    """A cached dataset with at least `paths` curated paths (made once, then reused).

    Only what retrieval reads is written: `mechanisms`, and `curated` made from them by
    re-simulation (a fraction of the bytes a path takes with every table). The cache is under
    `$XDG_CACHE_HOME/links-ray` unless `folder` names one.
    """
    from links_ray.cluster.curation import curate
    from links_ray.cluster.generation import generate

    root = folder or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")),
        "links-ray",
        f"retrieve-{paths}",
    )
    if _curated_rows(root) >= paths:
        return root
    # A run that falls short is made again, larger.
    mechanisms = max(1000, int(paths / CURATED_PER_MECHANISM))
    while True:
        generate(root, mechanisms, seed=2024, progress=False, tables=("mechanisms",))
        curate(root, progress=False, tables=("curated",))
        curated = _curated_rows(root)
        if curated >= paths:
            return root
        shutil.rmtree(root)
        mechanisms = int(mechanisms * 1.2 * paths / max(curated, 1))


def _curated_rows(root: str) -> int:
    """Curated paths committed at `root` (0 if there is no dataset there)."""
    from links_ray.data.commit import committed_shards
    from links_ray.data.store import Store

    if not os.path.isdir(root):
        return 0
    markers = committed_shards(Store.open(root, writable=False), "curation")
    return sum(marker["rows"].get("curated", 0) for marker in markers.values())


def folder_bytes(folder: str) -> int:
    """Bytes of every file under `folder` (a local path)."""
    return sum(
        os.path.getsize(os.path.join(root, name))
        for root, _, names in os.walk(folder)
        for name in names
    )
