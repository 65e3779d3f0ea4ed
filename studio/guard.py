"""Who may talk to a running studio: its own page, opened with its token, and nothing else.

viser serves its page and its WebSocket on one port and accepts any Origin and any
Host header. A studio can write files, so every HTTP request and WebSocket handshake
passes ``Guard.admit`` first, before viser sees it (websockets' ``process_request``):

- the Host header must name the address the studio listens on (for a loopback
  studio also ``localhost``; for a wildcard address any IP literal or this
  machine's name), at the port it listens on: a DNS-rebinding page sends its own
  domain name and is refused;
- a WebSocket handshake must come from the studio's own page: its Origin must be
  ``http://`` + that Host, so no other site open in the same browser can connect;
- every request must carry the launch's secret token, as ``?token=`` in the
  printed URL (as Jupyter does) or in the cookie that the page's first response sets
  (``SameSite=Strict``, ``HttpOnly``).

Refusals are answered 403 before anything is read and logged to stderr. viser has no
hook for this, so ``guarded_server`` passes the check to the ``serve`` call that viser
makes while it starts (the smallest wrapper around its server; tests/test_guard.py
covers it, and fails if the private module it wraps moves: setup.cfg pins the viser
releases it was written against); nothing else of viser changes.
"""

from __future__ import annotations

import contextlib
import gzip
import hmac
import html
import ipaddress
import logging
import secrets
import socket
import sys
import threading
from http import HTTPStatus
from http.cookies import CookieError, SimpleCookie
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from websockets.datastructures import Headers
from websockets.http11 import Response

TOKEN_PARAM = "token"
MAX_MESSAGE = 1 << 20  # bytes of one message from a browser (camera moves, panel edits)
_LOOPBACK_NAMES = frozenset({"localhost"})
_PATCH = threading.Lock()  # one studio starts at a time (``guarded_server``)


def log(message: str) -> None:
    print(f"palette-studio: {message}", file=sys.stderr, flush=True)


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is this machine only."""
    if host.lower() in _LOOPBACK_NAMES:
        return True
    return _is_ip(host) and ipaddress.ip_address(host).is_loopback


def _split_host(value: str) -> tuple[str, int | None]:
    """``"[::1]:8080"`` -> ("::1", 8080); ("", None) when malformed."""
    try:
        parts = urlsplit("//" + value)
        return (parts.hostname or "").lower(), parts.port
    except ValueError:
        return "", None


class Guard:
    """The admission rule of one studio.

    Parameters
    ----------
    host : str
        The address the studio listens on.
    title : str
        The page's title (the browser tab), instead of viser's.
    token : str, optional
        The launch's secret; a fresh random one by default.
    """

    def __init__(self, host: str, title: str, token: str | None = None):
        self.token = token or secrets.token_urlsafe(24)
        self.title = title
        host = host.strip("[]").lower()
        self.wildcard = _is_ip(host) and ipaddress.ip_address(host).is_unspecified
        names = {host}
        if is_loopback(host) or self.wildcard:
            names |= {"localhost", "127.0.0.1", "::1"}
        if self.wildcard:
            names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        self.names = frozenset(names)
        self._page: dict[bool, bytes] = {}

    def cookie_name(self, port: int) -> str:
        return f"palette-studio-{port}"

    def _host_allowed(self, value: str, port: int) -> bool:
        name, given_port = _split_host(value)
        if given_port != port or not name:
            return False
        return name in self.names or (self.wildcard and _is_ip(name))

    def _token_of(self, request, port: int) -> str:
        query = parse_qs(urlsplit(request.path).query).get(TOKEN_PARAM, [""])[0]
        if query:
            return query
        try:
            cookie = SimpleCookie(request.headers.get("Cookie", ""))
        except CookieError:
            return ""
        morsel = cookie.get(self.cookie_name(port))
        return morsel.value if morsel else ""

    def refusal(self, request, port: int) -> str | None:
        """Why ``request`` (a websockets ``Request``) to a studio on ``port`` is refused;
        None to admit it."""
        host = request.headers.get("Host", "")
        if not self._host_allowed(host, port):
            return f"Host {host!r} is not this studio's address"
        if request.headers.get("Upgrade", "").lower() == "websocket":
            origin = request.headers.get("Origin", "")
            if origin.lower() != f"http://{host}".lower():
                return f"a WebSocket from origin {origin or 'none'!r}, not the studio's page"
        if not hmac.compare_digest(self._token_of(request, port).encode(), self.token.encode()):
            return "no valid token (open the URL the studio printed)"
        return None

    def admit(self, connection, request, serve_http):
        """websockets' ``process_request``: 403 for a refused request, the studio's page
        for ``/``, viser's handler (``serve_http``) for the rest."""
        port = connection.local_address[1]
        peer = connection.remote_address[0] if connection.remote_address else "?"
        why = self.refusal(request, port)
        if why is not None:
            log(f"refused {request.path.split('?')[0]!r} from {peer}: {why}")
            return connection.respond(HTTPStatus.FORBIDDEN, f"palette-studio: {why}\n")
        if request.headers.get("Upgrade", "").lower() == "websocket":
            log(f"connected: {peer}")
            return None
        path = urlsplit(request.path).path
        response = (self._page_response(connection, request) if path in ("/", "/index.html")
                    else serve_http(connection, request))
        if response is not None:
            response.headers["Set-Cookie"] = (f"{self.cookie_name(port)}={self.token}; Path=/; "
                                              "HttpOnly; SameSite=Strict")
            response.headers["Referrer-Policy"] = "no-referrer"  # the token stays here
        return response

    def _page_response(self, connection, request):
        """viser's page with the studio's title, gzipped when the browser accepts it."""
        zipped = "gzip" in request.headers.get("Accept-Encoding", "")
        if zipped not in self._page:
            import viser

            page = (Path(viser.__file__).parent / "client" / "build" / "index.html").read_text()
            page = page.replace("<title>Viser</title>",
                                f"<title>{html.escape(self.title)}</title>", 1).encode()
            self._page[zipped] = gzip.compress(page) if zipped else page
        body = self._page[zipped]
        headers = Headers({"Content-Type": "text/html; charset=utf-8",
                           "Content-Length": str(len(body)),
                           "Content-Encoding": "gzip" if zipped else "identity"})
        return Response(HTTPStatus.OK, "OK", headers, body)


class _Override:
    """``obj`` with some attributes replaced."""

    def __init__(self, obj, **attributes):
        self._obj = obj
        self.__dict__.update(attributes)

    def __getattr__(self, name):
        return getattr(self._obj, name)


class _NoHandshakeNoise(logging.Filter):
    """A browser's speculative connection that closes unused is not an error worth a trace."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "opening handshake failed"


@contextlib.contextmanager
def guarded_server(guard: Guard):
    """While the block runs (create the ``viser.ViserServer`` in it), viser's WebSocket server
    starts with ``guard.admit`` in front of its HTTP handler and a ``MAX_MESSAGE`` limit."""
    from viser.infra import _infra

    websockets = _infra.websockets

    def serve(handler, *args, process_request=None, **options):
        def admit(connection, request):
            return guard.admit(connection, request, process_request or (lambda c, r: None))

        options["max_size"] = MAX_MESSAGE
        return websockets.asyncio.server.serve(handler, *args, process_request=admit, **options)

    patched = _Override(websockets, asyncio=_Override(
        websockets.asyncio, server=_Override(websockets.asyncio.server, serve=serve)))
    server_log = logging.getLogger("websockets.server")
    if not any(isinstance(f, _NoHandshakeNoise) for f in server_log.filters):
        server_log.addFilter(_NoHandshakeNoise())
    with _PATCH:
        _infra.websockets = patched
        try:
            yield
        finally:
            _infra.websockets = websockets
