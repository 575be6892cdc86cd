"""The FastAPI app `api` that the Serve deployments answer with, assembled in one place.

It takes the routes of `serve.http.routes` in, puts the guards of `serve.http.middleware` before
them, answers every refusal as a 4xx `{"error": "<what is wrong>"}` (`ApiError`, and FastAPI's own
refusals of unknown routes and methods and malformed parameters), and serves the document of
`serve.http.openapi` at `GET /openapi.json`. Nothing here imports Ray: the deployments
(`serve.deployments`) take this app in with `serve.ingress`.
"""

from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from links_ray import __version__
from links_ray.serve.http.middleware import HostGuard, InternalErrorGuard
from links_ray.serve.http.openapi import TITLE, openapi_document
from links_ray.serve.http.responses import ApiError, JsonResponse, error_response
from links_ray.serve.http.routes import router

# `/openapi.json` describes the routes; no interactive docs page, which would load its
# scripts from a CDN.
api = FastAPI(
    title=TITLE,
    version=__version__,
    docs_url=None,
    redoc_url=None,
    openapi_url="/openapi.json",
    default_response_class=JsonResponse,
)
api.include_router(router)
api.add_middleware(InternalErrorGuard)
api.add_middleware(HostGuard)  # added last, so it runs first


def api_openapi() -> dict[str, Any]:
    """The app's OpenAPI document (`serve.http.openapi`), made once: by the first request for it,
    after Serve has bound the routes to the replica."""
    if api.openapi_schema is None:
        api.openapi_schema = openapi_document(api.routes)
    return api.openapi_schema


api.openapi = api_openapi  # type: ignore[method-assign]


@api.exception_handler(ApiError)
async def _api_error(request: Request, exc: ApiError) -> JsonResponse:
    response = error_response(exc.status, exc.message, **exc.extra)
    response.headers.update(exc.headers)
    return response


@api.exception_handler(StarletteHTTPException)
async def _http_error(request: Request, exc: StarletteHTTPException) -> JsonResponse:
    response = error_response(exc.status_code, str(exc.detail).lower())
    if exc.headers:
        response.headers.update(exc.headers)
    return response


@api.exception_handler(RequestValidationError)
async def _validation_error(request: Request, exc: RequestValidationError) -> JsonResponse:
    problems = [
        f"{'.'.join(str(part) for part in error.get('loc', ()))}: {error.get('msg', 'invalid')}"
        for error in exc.errors()[:5]
    ]
    return error_response(400, "invalid request: " + "; ".join(problems))
