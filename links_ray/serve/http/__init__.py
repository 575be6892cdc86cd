"""The HTTP layer, without Ray: the routes (`routes`), the bodies they take (`schemas` as
OpenAPI shows them, `bodies` as they are read and checked), the answers (`responses`), the
middleware (`middleware`), the admission of costly work (`admission`), every refusal limit
(`limits`), the OpenAPI document (`openapi`), the ASGI app assembled from them (`asgi`), and
the request gate `links serve` puts before Serve (`gate`, `gate_wire`). The retrieval behind
the routes is a `backend.RetrievalBackend`; the Serve deployments provide it.
"""
