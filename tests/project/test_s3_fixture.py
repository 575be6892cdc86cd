"""Tests of the SeaweedFS S3 fixtures: pyarrow and boto3 reach the store from env only."""

from __future__ import annotations

import socket
import time
from typing import Any

import boto3
import botocore.exceptions
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.fs as pafs
import pyarrow.parquet as pq
import pytest
from botocore.config import Config


def _table() -> pa.Table:
    """A small table with a partition column."""
    return pa.table(
        {
            "part": ["a", "a", "b", "b", "b"],
            "x": pa.array([1, 2, 3, 4, 5], pa.int64()),
            "y": [0.5, 1.5, 2.5, 3.5, 4.5],
        }
    )


def _closed_port() -> int:
    """A port on 127.0.0.1 that nothing listens on."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_parquet_roundtrip_env_only(s3_env: str) -> None:
    """from_uri with env-only config writes a Parquet file and reads it back identical."""
    uri = f"{s3_env}/some/prefix/file.parquet"
    fs, path = pafs.FileSystem.from_uri(uri)
    assert isinstance(fs, pafs.S3FileSystem)
    table = _table()
    pq.write_table(table, path, filesystem=fs)

    assert fs.get_file_info(path).type == pafs.FileType.File
    assert pq.read_table(path, filesystem=fs).equals(table)
    bucket, key = uri.removeprefix("s3://").split("/", 1)
    head = boto3.client("s3").head_object(Bucket=bucket, Key=key)
    assert head["ContentLength"] == fs.get_file_info(path).size


def test_endpoint_from_env_only_via_from_uri(s3_env: str, s3_server: Any) -> None:
    """from_uri takes AWS_ENDPOINT_URL; a bare S3FileSystem() does not (no request is sent)."""
    fs, _ = pafs.FileSystem.from_uri(f"{s3_env}/x")
    assert fs.__reduce__()[1][0]["endpoint_override"] == s3_server.endpoint
    assert pafs.S3FileSystem().__reduce__()[1][0]["endpoint_override"] == ""


def test_hive_partitioned_dataset(s3_env: str) -> None:
    """A hive-partitioned folder written to S3 reads back through dataset(uri)."""
    uri = f"{s3_env}/prefix/table"
    fs, path = pafs.FileSystem.from_uri(uri)
    table = _table()
    ds.write_dataset(
        table,
        path,
        filesystem=fs,
        format="parquet",
        partitioning=["part"],
        partitioning_flavor="hive",
    )
    names = sorted(
        info.path.removeprefix(path + "/")
        for info in fs.get_file_info(pafs.FileSelector(path, recursive=True))
        if info.type == pafs.FileType.File
    )
    assert [n.split("/")[0] for n in names] == ["part=a", "part=b"]

    got = ds.dataset(uri, format="parquet", partitioning="hive").to_table()
    got = got.select(table.column_names).sort_by("x")
    assert got.column("x").to_pylist() == table.column("x").to_pylist()
    assert got.column("y").to_pylist() == table.column("y").to_pylist()
    assert got.column("part").to_pylist() == table.column("part").to_pylist()


def test_tmp_file_visible_only_after_move(s3_env: str) -> None:
    """A ``_tmp`` file is skipped by dataset discovery until moved to its final name."""
    uri = f"{s3_env}/prefix/moved"
    fs, path = pafs.FileSystem.from_uri(uri)
    pq.write_table(pa.table({"x": [1, 2]}), f"{path}/part-0.parquet", filesystem=fs)
    pq.write_table(pa.table({"x": [3, 4]}), f"{path}/_tmp-part-1.parquet", filesystem=fs)

    before = ds.dataset(uri, format="parquet")
    assert [f.rsplit("/", 1)[-1] for f in before.files] == ["part-0.parquet"]
    assert sorted(before.to_table().column("x").to_pylist()) == [1, 2]

    fs.move(f"{path}/_tmp-part-1.parquet", f"{path}/part-1.parquet")
    assert fs.get_file_info(f"{path}/_tmp-part-1.parquet").type == pafs.FileType.NotFound
    after = ds.dataset(uri, format="parquet")
    assert sorted(f.rsplit("/", 1)[-1] for f in after.files) == [
        "part-0.parquet",
        "part-1.parquet",
    ]
    assert sorted(after.to_table().column("x").to_pylist()) == [1, 2, 3, 4]


@pytest.mark.parametrize(
    ("key", "secret", "pyarrow_code", "boto_code"),
    [
        (None, "wrong-secret", "SIGNATURE_DOES_NOT_MATCH", "SignatureDoesNotMatch"),
        ("AKNOSUCHKEY", "wrong-secret", "INVALID_ACCESS_KEY_ID", "InvalidAccessKeyId"),
    ],
    ids=["bad-secret", "unknown-key"],
)
def test_wrong_credentials_error(
    s3_env: str,
    monkeypatch: pytest.MonkeyPatch,
    key: str | None,
    secret: str,
    pyarrow_code: str,
    boto_code: str,
) -> None:
    """Wrong credentials raise OSError (pyarrow) and ClientError (boto3) with AWS codes."""
    if key is not None:
        monkeypatch.setenv("AWS_ACCESS_KEY_ID", key)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", secret)
    bucket = s3_env.removeprefix("s3://")
    fs, path = pafs.FileSystem.from_uri(f"{s3_env}/prefix")

    with pytest.raises(OSError, match=pyarrow_code):
        fs.get_file_info(pafs.FileSelector(path, allow_not_found=True))
    # HeadObject has no error body: pyarrow reports only ACCESS_DENIED.
    with pytest.raises(OSError, match="ACCESS_DENIED during HeadObject"):
        fs.get_file_info(f"{path}/file.parquet")
    with pytest.raises(OSError, match=pyarrow_code):
        pq.write_table(pa.table({"x": [1]}), f"{path}/f.parquet", filesystem=fs)
    # A new session: boto3's default one keeps the credentials it resolved first.
    with pytest.raises(botocore.exceptions.ClientError) as info:
        boto3.session.Session().client("s3").list_objects_v2(Bucket=bucket)
    assert info.value.response["Error"]["Code"] == boto_code


def test_unreachable_endpoint_fails_fast(monkeypatch: pytest.MonkeyPatch) -> None:
    """A closed port fails within seconds with short timeouts and a single attempt."""
    endpoint = f"http://127.0.0.1:{_closed_port()}"
    monkeypatch.setenv("AWS_ENDPOINT_URL", endpoint)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "AKUNREACHABLE")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "unused")
    monkeypatch.setenv("AWS_REGION", "us-east-1")
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")

    fs = pafs.S3FileSystem(
        endpoint_override=endpoint,
        connect_timeout=1,
        request_timeout=2,
        retry_strategy=pafs.AwsStandardS3RetryStrategy(max_attempts=1),
    )
    start = time.monotonic()
    with pytest.raises(OSError, match=r"NETWORK_CONNECTION.*Could not connect to server"):
        fs.get_file_info("bucket/key")
    assert time.monotonic() - start < 3

    client = boto3.client(
        "s3", config=Config(connect_timeout=1, read_timeout=2, retries={"max_attempts": 1})
    )
    start = time.monotonic()
    with pytest.raises(botocore.exceptions.EndpointConnectionError, match="Could not connect"):
        client.list_buckets()
    assert time.monotonic() - start < 3
