"""The dataset on disk: table schemas, the store (a folder or S3), the commit protocol, the
generation plan and the rows it writes, and reading committed rows back.

pyarrow and the engine: no Ray.
"""
