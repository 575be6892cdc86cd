"""The API's OpenAPI document (`GET /openapi.json`, and the docs' HTTP reference page).

Built from the app's routes without Ray: the docs hook (docs/hooks/reference_pages.py) calls
`openapi_document` in a process that never starts Serve, and a replica serves the same
document (`serve.http.asgi.api_openapi`). FastAPI's own document is amended in three ways:

- the request bodies' schemas from `serve.http.schemas` are added, since the routes read their
  bodies themselves and FastAPI does not see their models;
- the routes are methods (`serve.http.routes.LinksApiRoutes`) whose `self` Serve binds to the
  replica when it takes the app in (`serve.ingress`); before that FastAPI takes `self` for a
  query parameter, which no client sends, so it is left out;
- FastAPI's 422 `{"detail"}` for a malformed parameter is the 400 `{"error"}` this API
  answers (`serve.http.asgi`), as `schemas.ErrorResponse` says.
"""

import json
from collections.abc import Sequence
from typing import Any

from fastapi.openapi.utils import get_openapi
from starlette.routing import BaseRoute

from links_ray import __version__
from links_ray.serve.http import schemas as bodies_described

#: The document's title; the app's too.
TITLE = "links-ray"
#: What the document says of the API as a whole.
DESCRIPTION = (
    "The HTTP API of docs/reference/contract.md. Every bound is a limit of GET /api/limits; "
    'a refused request gets a 4xx and {"error": "<what is wrong>"}.'
)
#: The answer to a malformed parameter, as documented.
ERROR_400 = {
    "description": "Bad Request",
    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}},
}


def openapi_document(routes: Sequence[BaseRoute]) -> dict[str, Any]:
    """The OpenAPI document of `routes` (an app's `routes`, whether or not Serve has bound
    their `self`), with the request bodies' schemas; a new one each call."""
    document = get_openapi(
        title=TITLE, version=__version__, description=DESCRIPTION, routes=list(routes)
    )
    schemas = document.setdefault("components", {}).setdefault("schemas", {})
    for item in document["paths"].values():
        for operation in item.values():
            parameters = [
                parameter
                for parameter in operation.get("parameters", [])
                if (parameter["name"], parameter["in"]) != ("self", "query")
            ]
            if parameters:
                operation["parameters"] = parameters
            else:
                operation.pop("parameters", None)
            answers = operation.get("responses", {})
            if "HTTPValidationError" in json.dumps(answers.get("422", {})):
                answers.pop("422")
                if parameters:  # a route whose only parameter was `self` refuses none
                    answers.setdefault("400", ERROR_400)
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    for model in bodies_described.REQUEST_MODELS.values():
        schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        schemas.update(schema.pop("$defs", {}))
        schemas[model.__name__] = schema
    return document
