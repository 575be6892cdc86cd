"""`links serve ROOT`: the Ray Serve app, the HTTP API and the studio at / (`links_ray.serve`)."""

from __future__ import annotations

import argparse

from links_ray.cli.arguments import port, positive_float, positive_int
from links_ray.cli.kernels import note_compiling


def add_command(commands: argparse._SubParsersAction) -> None:
    """Register `links serve` on the `links` command's subparsers."""
    serve = commands.add_parser("serve", help="Ray Serve app: the HTTP API and the studio at /")
    serve.add_argument("root", help="dataset root: a folder or s3://...")
    serve.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    serve.add_argument("--port", type=port, default=8000, help="port (default 8000)")
    serve.add_argument(
        "--replicas",
        type=positive_int,
        default=1,
        help="replicas of the app (with --shards: of the gateway and of each partition; default 1)",
    )
    serve.add_argument(
        "--shards",
        type=positive_int,
        default=None,
        help="split the index into N partitions, each served by its own deployment, which "
        "the gateway asks at once (default: one index in the gateway)",
    )
    serve.add_argument(
        "--shard-cpus",
        type=positive_float,
        default=None,
        help="CPUs Ray reserves for each partition replica (default 1, or on a Ray this "
        "command starts, if that does not fit, an equal share of what the gateway leaves)",
    )
    serve.add_argument(
        "--shard-memory-gb",
        type=positive_float,
        default=None,
        help="memory Ray reserves for each partition replica, in GB (default none)",
    )
    serve.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a host name the server answers to besides its addresses and localhost (the name "
        "a proxy or DNS gives it; repeatable; * for any): others get 400",
    )
    serve.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """`links serve`: run the app until interrupted."""
    from links_ray.serve.app import run_server  # imports Ray Serve: only when asked for

    note_compiling("serve")
    run_server(
        args.root,
        host=args.host,
        port=args.port,
        replicas=args.replicas,
        shards=args.shards,
        shard_cpus=args.shard_cpus,
        shard_memory_gb=args.shard_memory_gb,
        allowed_hosts=args.allow_host,
    )
