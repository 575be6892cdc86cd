"""Retrieval: the index of curated paths, its compiled kernels, and answers in a query's frame.

`search.index` is the face (`RetrievalIndex`); behind it `arrays` (`IndexArrays`, what a query
reads), `query` (the query pipeline), `build`, `cache` (the saved index and its lease),
`brute_force` (the exact truth), `placement` (results in the query's frame), `kernels`,
`mechanisms` and `reduced`. Imports run one way: the face passes the rooms arrays, and no room
imports the face.

The engine and the data layer: no Ray.
"""
