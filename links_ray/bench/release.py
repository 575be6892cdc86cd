"""`links bench import-release`: the LINKS release's files imported into a links-ray root.

The release's four files are written first, from the cached benchmark data set's mechanisms
(`retrieval_dataset`), by `links export-dataset --format release` (`export_release_files`): the
first `batches` batches of BATCH mechanisms each, in mechanism_id order, joint counts mixed, as
the release holds them. Then they are imported (`import_release`), timed, in a child process
whose peak memory is the import's own (the export's batch is not counted in it).

Reported: mechanisms, seconds, mechanisms a second and peak resident memory of the import and
of the export, and the import summary's check against the release's trajectories.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from links_ray.bench.machine import machine_info

#: Mechanisms a batch, as in the release.
BATCH = 100_000

#: The child that imports and reports its own peak memory (`high_water_bytes`: `ru_maxrss` is
#: no measure here, as Linux carries it across the exec that starts the child, so it would
#: report the exporting parent's peak).
_IMPORT = """
import json, sys, time
from links_ray.bench.release import high_water_bytes
from links_ray.release.importer import import_release
start = time.perf_counter()
summary = import_release(sys.argv[1], sys.argv[2])
seconds = time.perf_counter() - start
print(json.dumps({"seconds": seconds, "peak_bytes": high_water_bytes(), "summary": summary}))
"""


def high_water_bytes() -> int:
    """This process's peak resident memory so far (Linux's VmHWM)."""
    status = Path("/proc/self/status").read_text()
    return int(re.search(r"VmHWM:\s+(\d+) kB", status)[1]) * 1024


def bench_import(batches: int = 2, paths: int = 1_000_000) -> dict:
    """Export `batches` batches of BATCH mechanisms of the cached data set of `paths` curated
    paths in the release's layout, import them, and report both (the module docstring)."""
    from links_ray.bench.data import retrieval_dataset
    from links_ray.release.pickled_export import export_release_files

    root = retrieval_dataset(paths)
    with tempfile.TemporaryDirectory(prefix="links-bench-release-") as folder:
        release, imported = Path(folder, "release"), Path(folder, "root")
        start = time.perf_counter()
        exported = export_release_files(root, str(release), chunk_size=BATCH, batches=batches)
        export_s = time.perf_counter() - start
        export_peak = high_water_bytes()  # the bench's own, the export's being the largest
        sizes = {file.name: file.stat().st_size for file in release.iterdir()}
        done = subprocess.run(
            [sys.executable, "-c", _IMPORT, str(release), str(imported)],
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode != 0:
            raise RuntimeError(f"the import failed: {done.stderr.strip().splitlines()[-1:]}")
        measured = json.loads(done.stdout.strip().splitlines()[-1])
    mechanisms = exported["mechanisms"]
    return {
        "mechanisms": mechanisms,
        "batches": len(exported["batches"]),
        "batch_size": BATCH,
        "release_bytes": sizes,
        "export_s": export_s,
        "export_per_s": mechanisms / export_s,
        "export_peak_bytes": export_peak,
        "import_s": measured["seconds"],
        "import_per_s": mechanisms / measured["seconds"],
        "import_peak_bytes": measured["peak_bytes"],
        "summary": measured["summary"],
        "machine": machine_info(),
    }


def format_import(result: dict) -> str:
    """The import bench in a few lines."""
    summary = result["summary"]
    check = {
        key: summary[key]
        for key in ("agreeing", "disagreeing", "locking_at_release_angles", "negatives")
    }
    gib = result["import_peak_bytes"] / 2**30
    files = ", ".join(
        f"{name} {size / 2**30:.2f} GiB" for name, size in result["release_bytes"].items()
    )
    return "\n".join(
        [
            f"{result['mechanisms']:,} mechanisms in {result['batches']} release batches of "
            f"{result['batch_size']:,} ({files})",
            f"import: {result['import_s']:.0f} s, {result['import_per_s']:,.0f} mechanisms/s, "
            f"peak memory {gib:.2f} GiB",
            f"export: {result['export_s']:.0f} s, {result['export_per_s']:,.0f} mechanisms/s, "
            f"peak memory {result['export_peak_bytes'] / 2**30:.2f} GiB",
            f"check against the release's trajectories: {json.dumps(check)}, worst error "
            f"{summary['worst_error']:.2g}",
        ]
    )
