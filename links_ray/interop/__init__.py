"""Interop: mechanisms to and from other linkage libraries, and drawing files (SVG, DXF).

Above the engine only (no Ray, pyarrow or pandas): a module here imports its library when one
of its functions is called, so the package works without an optional one (pylinkage).
"""
