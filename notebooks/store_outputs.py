"""Run the notebooks top to bottom and store them with their outputs, so that the repository
page shows their figures.

    python notebooks/store_outputs.py [NAME ...]

(from the repository root, with links-ray and its `notebooks` extra installed; all four
notebooks by default). Each runs in a fresh kernel, its outputs cleared first, in a temporary
working directory that is removed after, at the sizes its first cell reads from the
environment (small by default), on its own Ray and store: Ray addresses and S3 settings are
left out of its environment. Every code cell is stamped with the SHA-256 of its source
(`metadata.links.source_sha256`): `tests/project/test_notebooks.py` checks the stored outputs come
from the cells as they are.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
import time
from pathlib import Path

import nbclient
import nbformat

NOTEBOOKS = Path(__file__).resolve().parent
NAMES = ("01_quickstart", "02_paper_figures", "03_cluster_and_s3", "04_training_data")
#: Seconds one cell may take (a whole notebook takes one to a few minutes).
CELL_TIMEOUT_S = 600
#: Settings that would point a notebook at a Ray or an S3 store other than its own.
FOREIGN = ("RAY_ADDRESS", "LINKS_NB_RAY_ADDRESS", "LINKS_NB_S3_URI")


def notebook_env(**extra: str) -> dict[str, str]:
    """This environment without Ray addresses or S3 settings, plus `extra`."""
    env = {
        name: value
        for name, value in os.environ.items()
        if name not in FOREIGN and not name.startswith("AWS_")
    }
    env.update(extra)
    return env


def source_digest(source: str) -> str:
    return hashlib.sha256(source.encode()).hexdigest()


def run_notebook(
    name: str, workdir: Path, env: dict[str, str]
) -> tuple[nbformat.NotebookNode, float]:
    """Execute a cleared copy of notebook `name` in `workdir`; returns it with its outputs
    (each code cell stamped with its source's digest) and the seconds it took."""
    notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    for cell in notebook.cells:
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
            cell.metadata.pop("links", None)
    client = nbclient.NotebookClient(
        notebook,
        kernel_name="python3",
        timeout=CELL_TIMEOUT_S,
        record_timing=False,  # no timestamps: a rerun changes only what it shows
        resources={"metadata": {"path": str(workdir)}},
    )
    start = time.perf_counter()
    client.execute(env=env)
    for cell in notebook.cells:
        if cell.cell_type == "code":
            cell.metadata["links"] = {"source_sha256": source_digest(cell.source)}
    return notebook, time.perf_counter() - start


def main(names: list[str]) -> None:
    for name in names or NAMES:
        with tempfile.TemporaryDirectory(prefix=f"links-{name}-") as workdir:
            notebook, seconds = run_notebook(name, Path(workdir), notebook_env())
        nbformat.write(notebook, NOTEBOOKS / f"{name}.ipynb")
        size = (NOTEBOOKS / f"{name}.ipynb").stat().st_size
        print(f"{name}: ran in {seconds:.0f} s, stored {size / 1e3:.0f} KB")


if __name__ == "__main__":
    main(sys.argv[1:])
