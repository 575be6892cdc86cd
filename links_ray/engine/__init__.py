"""The engine: numpy and numba only (no Ray, no pyarrow, no files), so it runs the same in a test,
a notebook, a Ray actor or a Serve replica.

A base that every room shares, and three rooms, each importing only the ones before it:

- the base: `inputs` (the shared limits on user input and their checks), `buffers` (the checks
  of the buffers kernels are given), `node_kinds` (the kinds of joint), `cpus` (threads a
  process may keep busy);
- `kinematics`: mechanisms, topologies, the compiled solver, turning, paths, position sampling,
  transmission angles, the reference solver;
- `fabrication`: drawings in millimetres, collisions between bars, layer plans, kits;
- `synthesis`: retrieval's candidates refined toward a drawing, within a budget, under a
  designer's constraints (`synthesis.refinement` is the local search and its kernels).
"""
