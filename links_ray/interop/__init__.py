"""Interop: mechanisms to and from other linkage libraries, each an optional extra.

Above the engine only (no Ray, pyarrow or pandas): a module here imports its library when one
of its functions is called, so the package works without it.
"""
