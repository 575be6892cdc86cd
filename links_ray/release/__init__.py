"""The LINKS release's own files, both ways: their format (`format`), a
reader that runs nothing they name (`pickles`, `unpickler`, `opcode_scan`), the import into a
links-ray root (`importer`) and the export of a root into them (`exporter`).

The release layer sits above data and the engine, beside search and cluster: pyarrow, numpy
and numba, no Ray. Only the command line imports it. Nothing is re-exported here: import a
name from the module that defines it.
"""
