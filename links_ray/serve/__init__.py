"""Serving on Ray Serve: the HTTP API, the web studio's files, and `links serve`.

Imports run one way, from the parts up to the assembly (no module imports one above it):

- `responses`: `ApiError` and compact JSON answers; `models`: the bodies for `/openapi.json`.
- `parsing`: request bodies read and checked; `guards`: the Host allow-list and the 500 guard.
- `admission`: the retrievals and syntheses a replica holds, and the line for its refiner.
- `handlers`: the routes (simulate, analyze, export, retrieve, synthesize, health, the studio).
- `openapi`: the API's OpenAPI document, built without Ray (the docs hook's, and the app's).
- `api`: the FastAPI app assembled: the routes, the guards, the errors, `/openapi.json`.
- `deployments`: the Serve deployments `LinksApi` (the gateway) and `IndexPartition`.
- `app`: building the application (`build_app`, `app_builder`) and launching it (`run_server`).
- `load_clients`: plain HTTP clients that load a server, for the serving benchmarks.
"""
