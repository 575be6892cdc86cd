"""The engine: mechanisms, the compiled solver, topologies, position sampling, path geometry,
and the limits on user input with their checks (`inputs`), which every layer above uses.

numpy and numba only: no Ray, no pyarrow, no files. It runs the same in a test, a notebook, a
Ray actor or a Serve replica.
"""
