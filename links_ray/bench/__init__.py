"""The benchmarks behind `links bench`: what each measures, against which target."""
