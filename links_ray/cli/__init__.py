"""The face: the `links` command, its benchmarks, the one-core demo and the figures."""
