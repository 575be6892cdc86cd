"""The notebooks run top to bottom on small sizes, and are stored with the outputs of such a
run of their current cells (so the repository page shows their figures).

Each runs, its stored outputs cleared first, in its own kernel (a separate process with its
own private Ray) in a temporary working directory, so the data it makes stays out of the
repository. The environment is this one without Ray addresses or S3 settings: the notebooks
start their own Ray and store. `notebooks/store_outputs.py` runs them the same way and stores
them.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import pytest

from tests.support.needs import missing, need_module

nbformat = need_module("nbformat", "pip install '.[notebooks]'")
need_module("nbclient", "pip install '.[notebooks]'")
kernelspec = need_module("jupyter_client.kernelspec", "pip install '.[notebooks]'")
try:
    kernelspec.KernelSpecManager().get_kernel_spec("python3")
except kernelspec.NoSuchKernel:
    missing("no Jupyter kernel 'python3' to run the notebooks in: pip install ipykernel")

NOTEBOOKS = Path(__file__).resolve().parents[2] / "notebooks"
sys.path.insert(0, str(NOTEBOOKS))
from store_outputs import NAMES, notebook_env, run_notebook, source_digest  # noqa: E402

#: What the four stored notebooks may weigh together: PNG figures, no data.
MAX_STORED_BYTES = 2_000_000


def outputs_text(notebook) -> str:
    return "\n".join(
        output.get("text", "") + str(output.get("data", {}).get("text/plain", ""))
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.outputs
    )


@pytest.mark.ray  # each notebook starts a Ray of its own
@pytest.mark.parametrize("name", ["01_quickstart", "02_paper_figures", "04_training_data"])
def test_notebook_runs(name: str, tmp_path: Path) -> None:
    notebook, seconds = run_notebook(name, tmp_path, notebook_env())
    print(f"{name}: {seconds:.1f} s")
    # A failing cell raises CellExecutionError above. The dataset lands in the working directory.
    datasets = list(tmp_path.glob("links-*/_links/summary.json"))
    assert len(datasets) == 1, "the notebook made no dataset in its working directory"
    assert "Traceback" not in outputs_text(notebook)


@pytest.mark.ray
@pytest.mark.s3  # the notebook starts a SeaweedFS of its own
def test_s3_notebook_starts_and_stops_its_own_store(tmp_path: Path) -> None:
    notebook, seconds = run_notebook("03_cluster_and_s3", tmp_path, notebook_env())
    print(f"03_cluster_and_s3: {seconds:.1f} s")
    text = outputs_text(notebook)
    started = re.findall(r"SeaweedFS \(pid (\d+)\) at http://127\.0\.0\.1:\d+", text)
    stopped = re.findall(r"SeaweedFS \(pid (\d+)\) stopped, exit code", text)
    assert started and started == stopped, text
    with pytest.raises(ProcessLookupError):  # stopped by its PID, and reaped
        os.kill(int(stopped[0]), 0)
    assert "s3://links/run-" in text
    assert not list(tmp_path.iterdir()), "the S3 notebook wrote into its working directory"


@pytest.mark.ray
def test_s3_notebook_uses_a_store_from_the_environment(s3_server, tmp_path: Path) -> None:
    """With AWS_ENDPOINT_URL set, notebook 03 uses that store instead of starting its own."""
    import boto3

    bucket = f"notebook-{os.getpid()}"
    env = notebook_env(
        AWS_ENDPOINT_URL=s3_server.endpoint,
        AWS_ACCESS_KEY_ID=s3_server.access_key,
        AWS_SECRET_ACCESS_KEY=s3_server.secret_key,
        AWS_REGION=s3_server.region,
        AWS_EC2_METADATA_DISABLED="true",
        LINKS_NB_S3_URI=f"s3://{bucket}/run",
        LINKS_NB_MECHANISMS="100",
    )
    notebook, seconds = run_notebook("03_cluster_and_s3", tmp_path, env)
    print(f"03_cluster_and_s3 on the session's store: {seconds:.1f} s")
    client = boto3.client(
        "s3",
        endpoint_url=s3_server.endpoint,
        aws_access_key_id=s3_server.access_key,
        aws_secret_access_key=s3_server.secret_key,
        region_name=s3_server.region,
    )
    listed = client.list_objects_v2(Bucket=bucket, Prefix="run/_links/")
    names = {item["Key"].rsplit("/", 1)[-1] for item in listed.get("Contents", [])}
    assert {"run.json", "summary.json", "curation_summary.json"} <= names
    assert s3_server.secret_key not in outputs_text(notebook)


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_with_the_outputs_of_a_clean_run(name: str) -> None:
    """Every code cell ran once, in order, from a fresh kernel (execution counts 1, 2, ...),
    as its source stands now (the digest stamped when it ran), and none failed."""
    notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbformat.validate(notebook)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert code, "a notebook without code"
    assert [cell.execution_count for cell in code] == list(range(1, len(code) + 1))
    for cell in code:
        stamp = cell.metadata.get("links", {}).get("source_sha256")
        assert stamp == source_digest(cell.source), (
            f"cell {cell.get('id')} changed since it ran: python notebooks/store_outputs.py"
        )
        kinds = {output.output_type for output in cell.outputs}
        assert "error" not in kinds, f"cell {cell.get('id')} failed"
        streams = [output for output in cell.outputs if output.output_type == "stream"]
        assert not any("Traceback" in output.text for output in streams)
    # The first code cell holds the sizes, read from the environment for real runs.
    assert "LINKS_NB_MECHANISMS" in code[0].source


def test_stored_notebooks_show_figures_and_stay_small() -> None:
    def figures(name: str) -> int:
        notebook = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
        return sum(
            "image/png" in output.get("data", {})
            for cell in notebook.cells
            if cell.cell_type == "code"
            for output in cell.outputs
        )

    assert figures("01_quickstart") >= 1 and figures("02_paper_figures") >= 1
    assert sum((NOTEBOOKS / f"{name}.ipynb").stat().st_size for name in NAMES) < MAX_STORED_BYTES
