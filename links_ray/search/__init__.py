"""Retrieval: the index of curated paths, its compiled kernels, and answers in a query's frame.

The engine and the data layer: no Ray.
"""
