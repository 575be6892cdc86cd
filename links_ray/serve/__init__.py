"""Serving on Ray Serve: the HTTP API, the web studio's files, and `links serve`."""
