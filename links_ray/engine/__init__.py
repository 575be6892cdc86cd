"""The engine: mechanisms, the compiled solver, topologies, position sampling, path geometry.

numpy and numba only: no Ray, no pyarrow, no files. It runs the same in a test, a notebook, a
Ray actor or a Serve replica.
"""
