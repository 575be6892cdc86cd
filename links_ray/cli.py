"""The `links` command line: parses arguments and calls library functions.

Errors a user can cause end as one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from links_ray import bench
from links_ray.demo import run_demo


def _bench_simulate(args: argparse.Namespace) -> None:
    result = bench.bench_simulate(repeats=args.repeats)
    print(json.dumps(result) if args.json else bench.format_simulate(result))


def _bench_sample(args: argparse.Namespace) -> None:
    result = bench.bench_sample(per_joint_count=args.topologies)
    print(json.dumps(result) if args.json else bench.format_sample(result))


def _demo(args: argparse.Namespace) -> None:
    summary = run_demo(args.out, mechanisms=args.mechanisms, seed=args.seed, sampler=args.sampler)
    print(json.dumps(summary, indent=2))


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="links", description="LINKS: planar linkage mechanisms and their paths."
    )
    commands = parser.add_subparsers(dest="command", required=True)

    demo = commands.add_parser(
        "demo", help="generate a few valid mechanisms with the engine and save them as JSON lines"
    )
    demo.add_argument("--out", default="links-demo", help="output folder (default links-demo)")
    demo.add_argument("--mechanisms", type=_positive_int, default=100)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--sampler", choices=["sequential", "rejection"], default="sequential")
    demo.set_defaults(run=_demo)

    bench_parser = commands.add_parser("bench", help="benchmarks")
    benches = bench_parser.add_subparsers(dest="bench", required=True)
    simulate = benches.add_parser(
        "simulate", help="the paper's Table 1: 10,000 random mechanisms, 200 steps"
    )
    simulate.add_argument("--json", action="store_true", help="print one JSON object")
    simulate.add_argument("--repeats", type=_positive_int, default=5)
    simulate.set_defaults(run=_bench_simulate)
    sample = benches.add_parser(
        "sample", help="position samplers: valid per core-second, candidates per valid"
    )
    sample.add_argument("--json", action="store_true", help="print one JSON object")
    sample.add_argument(
        "--topologies", type=_positive_int, default=10, help="topologies per joint count"
    )
    sample.set_defaults(run=_bench_sample)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.run(args)
    except (ValueError, OSError) as exc:
        print(f"links {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
