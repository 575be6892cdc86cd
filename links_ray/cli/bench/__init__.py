"""`links bench`: the benchmarks (`command` registers them), their cached dataset, and the
curves and drawings they measure with."""
