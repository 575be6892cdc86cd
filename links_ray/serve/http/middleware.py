"""The app's two middlewares: the Host allow-list (`HostGuard`) and the last word on
unexpected exceptions (`InternalErrorGuard`).

Anything unexpected is logged by exception type and location only (never a request body) and
answered 500 `{"error": "internal error"}`; the replica keeps serving. A request whose Host
header names a DNS name the server was not told of is refused 400 before its body is read
(DNS rebinding: `host_allowed`).
"""

import ipaddress

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from links_ray.serve.http.responses import error_response, logger, nosniff


class InternalErrorGuard:
    """ASGI middleware: an exception no handler took becomes 500 `{"error": "internal error"}`.

    Only the exception's type and where it was raised are logged: never its message, which
    may quote the request.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the app; answer 500 if it raises before it has started its response."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception as exc:
            frame = exc.__traceback__
            while frame is not None and frame.tb_next is not None:
                frame = frame.tb_next
            where = f"{frame.tb_frame.f_code.co_filename}:{frame.tb_lineno}" if frame else "unknown"
            logger.error(
                "links-ray API: unexpected %s at %s on %s %s",
                type(exc).__name__,
                where,
                scope.get("method"),
                scope.get("path"),
            )
            if started:
                raise
            await error_response(500, "internal error")(scope, receive, send)


#: Longest host name (RFC 1035), and the characters one may hold.
MAX_HOST_NAME_CHARS = 253
_HOST_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz0123456789-.")


def as_host_names(names: object) -> frozenset[str]:
    """Host names a server answers to besides addresses and `localhost` (`HostGuard`), lower
    case; `*` for any. ValueError naming a name that is not one."""
    if isinstance(names, str) or not isinstance(names, list | tuple | set | frozenset):
        raise ValueError(f"allowed hosts must be a list of host names, got {type(names).__name__}")
    checked = set()
    for name in names:
        text = name.strip().lower().rstrip(".") if isinstance(name, str) else ""
        if text != "*" and not (
            0 < len(text) <= MAX_HOST_NAME_CHARS
            and set(text) <= _HOST_NAME_CHARS
            and not text.startswith(("-", "."))
        ):
            shown = repr(name)[:80]
            raise ValueError(f"allowed hosts: {shown} is not a host name (or * for any)")
        checked.add(text)
    return frozenset(checked)


def host_name(header: str) -> str:
    """The host of a Host header, lower case, without its port or an IPv6 address's brackets."""
    text = header.strip().lower()
    if text.startswith("["):
        return text[1 : text.find("]")] if "]" in text else text
    return text.rsplit(":", 1)[0] if text.count(":") == 1 else text


def host_allowed(header: str | None, names: frozenset[str]) -> bool:
    """Whether a request that says it is for host `header` may be answered: an address (no
    DNS answer can stand behind it), `localhost` or a name under it, or one of `names` (`*`
    takes any). A DNS name the server was not told of is how a web page reaches a loopback
    server through a name of its own (DNS rebinding), so it is refused."""
    if header is None:
        return False
    host = host_name(header).rstrip(".")
    if "*" in names or host in names or host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def host_refusal(header: str | None) -> str:
    """What a request refused for its Host header `header` is told."""
    said = "no Host header" if header is None else f"Host {header[:80]!r}"
    return (
        f"{said}: this server answers its addresses, localhost and the names it is given "
        "(links serve --allow-host NAME, or the app's allowed_hosts)"
    )


#: The host names this process's app answers to besides addresses and localhost: set by the
#: gateway replica's constructor (`allow_host_names`), read by `HostGuard` on every request.
_allowed_host_names: frozenset[str] = frozenset()


def allow_host_names(names: object) -> None:
    """Have this process's app answer requests for `names` too (`as_host_names`); the gateway
    replica calls it with its `allowed_hosts` when it starts."""
    global _allowed_host_names
    _allowed_host_names = as_host_names(names)


class HostGuard:
    """ASGI middleware: a request whose Host header `host_allowed` refuses gets 400 with a
    JSON error saying how to let it in, before anything reads its body. The outermost of the
    app's middlewares, it gives every answer of the app `nosniff`'s header."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Refuse the request, or pass it on."""
        if scope["type"] == "http":
            send = nosniff(send)
            headers = dict(scope.get("headers") or ())
            raw = headers.get(b"host")
            header = raw.decode("latin-1") if raw is not None else None
            if not host_allowed(header, _allowed_host_names):
                await error_response(400, host_refusal(header))(scope, receive, send)
                return
        await self.app(scope, receive, send)
