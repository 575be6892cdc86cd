"""Serving on Ray Serve: the HTTP API, the web studio's files, and `links serve`.

- `app`: building the application (`build_app`, `app_builder`) and launching it (`run_server`).
- `deployments`: the deployments `LinksApi` and `IndexShard`, and their concurrency limits.
- `handlers`: the routes (simulate, analyze, export, retrieve, synthesize, health, the studio).
- `parsing`: request bodies read and checked; `models`: the same bodies for `/openapi.json`.
- `api`: the FastAPI app, its errors, JSON answers and OpenAPI document.
"""
