"""Retrieval: the index of curated paths, its compiled kernels, and answers in a query's frame.

`search.index` is the face (`RetrievalIndex`); behind it `query` (the query
pipeline), `build`, `cache` (the saved index and its lease), `brute_force` (the exact truth),
`placement` (results in the query's frame), `kernels` and `mechanisms`.

The engine and the data layer: no Ray.
"""
