"""The face: the `links` command, a module per command (listed in `main`), the arguments they
share, and the benchmarks (`bench/`)."""
