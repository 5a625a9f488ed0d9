"""Who may talk to a viewer: loopback only, or a token in the URL (issue 26).

A viewer hands out the session's photos and starts reconstructions on request.  Bound to a
loopback address (the default, ``127.0.0.1``) only this machine reaches it.  Bound to any other
address (``--host 0.0.0.0``, a LAN address) every request must carry the viewer's token: the page's
URL has ``?token=...`` (printed at start-up), and the first answer with it sets a cookie
(``HttpOnly``, ``SameSite=Strict``) that the page's own requests and its websocket then carry.
A request with neither (or a wrong token) gets ``403 Forbidden`` and nothing else: no page, no
websocket, no photo.

viser has no hook for this: its HTTP handler is a closure passed to ``websockets``'
``serve(process_request=...)``.  :func:`start_viser` wraps that argument while the server starts
(under a lock, for the few milliseconds of the start) and refuses to run the server when the wrap
did not take (a viser that starts differently): access control fails closed, never open.
"""

from __future__ import annotations

import hmac
import http
import ipaddress
import secrets
import socket
import threading
from typing import Any
from urllib.parse import parse_qs, urlsplit

from ..errors import OrganlabError

__all__ = ["COOKIE", "is_loopback", "new_token", "start_viser"]

#: Name of the cookie that carries the token after the first request.
COOKIE = "organlab_token"
_START_LOCK = threading.Lock()


def is_loopback(host: str) -> bool:
    """True when every address ``host`` names is a loopback address (only this machine reaches it).

    Examples
    --------
    >>> is_loopback("127.0.0.1"), is_loopback("0.0.0.0")
    (True, False)
    """
    try:
        return all(ipaddress.ip_address(info[4][0].split("%")[0]).is_loopback for info in socket.getaddrinfo(host, 0))
    except (OSError, ValueError, UnicodeError):
        return False


def new_token() -> str:
    """A fresh random token (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


def _request_token(request: Any) -> tuple[str | None, bool]:
    """The token a request carries and whether it came in the URL (not the cookie)."""
    query = parse_qs(urlsplit(request.path).query)
    if query.get("token"):
        return query["token"][0], True
    for header in request.headers.get_all("Cookie"):
        for part in header.split(";"):
            name, _, value = part.strip().partition("=")
            if name == COOKIE:
                return value, False
    return None, False


def _gate(inner: Any, token: str) -> Any:
    """``process_request`` that refuses a request without ``token`` and passes the others to ``inner``."""
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    expected = token.encode()

    def process_request(connection, request):
        given, in_url = _request_token(request)
        if given is None or not hmac.compare_digest(given.encode("utf-8", "surrogateescape"), expected):
            body = (b"organlab: this viewer needs its link with the token (printed where it was started)\n")
            return Response(http.HTTPStatus.FORBIDDEN, "Forbidden",
                            Headers({"Content-Type": "text/plain; charset=utf-8", "Content-Length": str(len(body))}),
                            body)
        response = inner(connection, request) if inner is not None else None
        if response is not None and in_url:
            response.headers["Set-Cookie"] = f"{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict"
        return response

    return process_request


def start_viser(*, host: str, port: int, label: str, verbose: bool, token: str | None) -> Any:
    """A ``viser.ViserServer`` on ``host:port``; with ``token``, every request must carry it.

    Raises
    ------
    OrganlabError
        ``token`` given and the gate could not be installed (the server is stopped again).
    """
    import rich
    import viser
    import websockets.asyncio.server as ws_server

    if token is None:
        return viser.ViserServer(host=host, port=port, label=label, verbose=verbose)
    with _START_LOCK:
        real = ws_server.serve
        installed = []

        def serve(*args, **kwargs):
            kwargs["process_request"] = _gate(kwargs.get("process_request"), token)
            installed.append(True)
            return real(*args, **kwargs)

        console = rich.get_console()
        quiet, console.quiet = console.quiet, True  # viser's banner shows the URL without the token: organlab prints it
        ws_server.serve = serve
        try:
            server = viser.ViserServer(host=host, port=port, label=label, verbose=verbose)
        finally:
            ws_server.serve = real
            console.quiet = quiet
    if not installed:
        server.stop()
        raise OrganlabError(f"cannot protect the viewer on {host} with a token (this viser starts its server "
                            "otherwise); use --host 127.0.0.1 and an SSH tunnel")
    return server
