"""Who may use a running viewer: its own page, at its own address, with its session's token.

Any web page a browser on this machine shows can open ``ws://127.0.0.1:PORT``, and a site whose
name is rebound to 127.0.0.1 can even read the answers; so, as a notebook server does, the
viewer answers only requests whose ``Host`` (and ``Origin``, when one is sent) name its own
address, and that carry the session's token: ``?token=`` in the page's URL, or the cookie that
such a page request sets (the page opens its websocket at its own URL without the query, and
the browser sends the cookie with it). Anything else gets HTTP 403: the page is not served and
the websocket handshake is refused.

viser hands its request handler straight to ``websockets``' server, with no hook for checks of
its own; :func:`install` therefore wraps the opening handshake of every connection accepted on a
guarded port, the one step every HTTP request and websocket of that server passes through.
"""

from __future__ import annotations

import contextlib
import errno
import http
import inspect
import io
import ipaddress
import logging
import secrets
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from http.cookies import CookieError, SimpleCookie
from typing import Any
from urllib.parse import parse_qs, urlsplit

from regnf.core.errors import RegnfError

log = logging.getLogger("regnf.viewer")

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
"""How a browser on this machine names a viewer bound to a loopback address."""
TOKEN_PARAMETER = "token"
"""Query parameter of the page's URL that carries the session's token."""


class TrustError(RegnfError):
    """A viewer that would not be safe or would not be where the user asked (one line)."""


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or address) is only reachable from this machine."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    """Whether ``host`` means every interface of this machine."""
    return host in ("", "0.0.0.0", "::", "[::]")


def check_host(host: str, allow_remote_edits: bool) -> None:
    """Refuse (:class:`TrustError`) to serve ``host`` beyond this machine without the user's
    acknowledgement that whoever reaches it can edit the stage."""
    if not is_loopback(host) and not allow_remote_edits:
        raise TrustError(f"--host {host}: others on the network could open the viewer and edit the stage; "
                         "pass --allow-remote-edits to accept that, or serve --host 127.0.0.1 only")


def _bound_sockets(host: str, port: int) -> list[socket.socket]:
    """Sockets bound to every address of ``host`` at ``port`` (as the server will bind them)."""
    infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    socks: list[socket.socket] = []
    try:
        for family, kind, proto, _, address in infos:
            s = socket.socket(family, kind, proto)
            socks.append(s)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server does
            if family == socket.AF_INET6:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            s.bind(address[:1] + (port,) + address[2:])
            port = port or s.getsockname()[1]  # port 0: the others take the first one's
    except BaseException:
        for s in socks:
            s.close()
        raise
    return socks


def free_port(host: str, port: int) -> int:
    """``port`` if it is free on ``host`` now, or (``port`` 0) a free one; a port in use, or an
    address this machine does not have, is a one-line :class:`TrustError`."""
    for _ in range(20):  # port 0 on a name with several addresses: the first's may be taken on another
        try:
            socks = _bound_sockets(host, port)
        except socket.gaierror as exc:
            raise TrustError(f"--host {host}: not a name or address of this machine ({exc.strerror})") from exc
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE and port == 0:
                continue
            if exc.errno == errno.EADDRINUSE:
                raise in_use(host, port) from exc
            if exc.errno == errno.EADDRNOTAVAIL:
                raise TrustError(f"--host {host}: not an address of this machine") from exc
            raise TrustError(f"cannot listen on {url_host(host)}:{port}: {exc.strerror or exc}") from exc
        chosen = socks[0].getsockname()[1]
        for s in socks:
            s.close()
        return int(chosen)
    raise TrustError(f"found no port free on every address of {host}")


def in_use(host: str, port: int) -> TrustError:
    """The error of a port that another program holds."""
    return TrustError(f"{url_host(host)}:{port} is in use by another program; choose another --port "
                      "(--port 0 picks a free one)")


def url_host(host: str) -> str:
    """``host`` as a URL writes it (an IPv6 address in brackets)."""
    try:
        return f"[{host.strip('[]')}]" if ipaddress.ip_address(host.strip("[]")).version == 6 else host
    except ValueError:
        return host


def _own_addresses() -> set[str]:
    """This machine's names and addresses, as URLs write them (for a viewer on every interface)."""
    names = {socket.gethostname(), socket.getfqdn()}
    addresses = set()
    for name in names:
        with contextlib.suppress(OSError):
            addresses |= {info[4][0] for info in socket.getaddrinfo(name, None)}
    with contextlib.suppress(OSError):
        addresses.add(outward_address())
    return {n.lower() for n in names} | {url_host(a) for a in addresses}


def outward_address() -> str:
    """The address other machines reach this one at (that of the route out; nothing is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.connect(("192.0.2.1", 9))  # a documentation address: only picks the interface
        return str(s.getsockname()[0])


def own_hosts(host: str, port: int) -> frozenset[str]:
    """The ``Host`` values (``name:port``, lower case) that name a viewer bound to ``host``."""
    names = {url_host(host).lower()}
    if is_loopback(host) or is_wildcard(host):
        names |= set(LOOPBACK_NAMES)
    if is_wildcard(host):
        names |= _own_addresses()
    elif not is_loopback(host):
        with contextlib.suppress(OSError):
            names |= {url_host(info[4][0]) for info in socket.getaddrinfo(host, None)}
    hosts = {f"{n}:{port}" for n in names}
    if port == 80:  # a browser leaves the default port out
        hosts |= names
    return frozenset(hosts)


def page_url(host: str, port: int, token: str) -> str:
    """The URL to open: an address that reaches the viewer, with the session's token."""
    if is_wildcard(host):
        try:
            name = outward_address()
        except OSError:
            name = socket.gethostname()
    elif host.lower() == "localhost":
        name = "127.0.0.1"
    else:
        name = host
    return f"http://{url_host(name)}:{port}/?{TOKEN_PARAMETER}={token}"


@dataclass(frozen=True)
class Guard:
    """The checks of one viewer's requests."""

    port: int
    """The port the viewer listens on."""
    hosts: frozenset[str]
    """Accepted ``Host`` values and ``Origin`` hosts (``name:port``, lower case)."""
    token: str
    """The session's token (``secrets.token_urlsafe``)."""

    @property
    def cookie(self) -> str:
        """Name of the cookie holding the token (cookies do not tell ports apart: one per port)."""
        return f"regnf-view-{self.port}"

    def _query_token(self, path: str) -> str | None:
        values = parse_qs(urlsplit(path).query).get(TOKEN_PARAMETER, [])
        return values[0] if len(values) == 1 else None

    def _cookie_token(self, cookie_headers: list[str]) -> str | None:
        jar: SimpleCookie = SimpleCookie()
        try:
            for header in cookie_headers:
                jar.load(header)
        except CookieError:
            return None
        return jar[self.cookie].value if self.cookie in jar else None

    def _is_token(self, value: str | None) -> bool:
        return value is not None and secrets.compare_digest(value.encode(), self.token.encode())

    def refusal(self, path: str, headers: Any) -> str | None:
        """Why a request (its path and ``websockets`` headers) is refused, or None."""
        host = headers.get_all("Host")
        if len(host) != 1 or host[0].lower() not in self.hosts:
            return f"Host {', '.join(host) or '(none)'} is not this viewer's address"
        for origin in headers.get_all("Origin"):
            parts = urlsplit(origin)
            if parts.scheme != "http" or parts.netloc.lower() not in self.hosts:
                return f"Origin {origin} is not this viewer's page"
        if not (self._is_token(self._query_token(path)) or self._is_token(self._cookie_token(headers.get_all("Cookie")))):
            return "no valid session token (open the URL the viewer printed)"
        return None

    def wrap(self, inner: Callable[..., Any] | None) -> Callable[..., Any]:
        """``process_request`` for ``websockets``: :meth:`refusal` first (HTTP 403), then ``inner``
        (viser's page server), whose page gets the token's cookie when asked with the token."""

        async def process_request(connection: Any, request: Any) -> Any:
            why = self.refusal(request.path, request.headers)
            what = "websocket" if request.headers.get_all("Upgrade") else "page request"
            if why is not None:
                log.warning("regnf view: refused a %s for %s: %s", what, urlsplit(request.path).path, why)
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"{why}\n")
            response = inner(connection, request) if inner is not None else None
            if inspect.isawaitable(response):
                response = await response
            if response is not None and self._is_token(self._query_token(request.path)):
                response.headers["Set-Cookie"] = f"{self.cookie}={self.token}; Path=/; HttpOnly; SameSite=Strict"
            return response

        return process_request


_GUARDS: dict[int, Guard] = {}
_LOCK = threading.Lock()
_ORIGINAL_HANDSHAKE: Callable[..., Any] | None = None


def _guarded_handshake(connection: Any, process_request: Any = None, *args: Any, **kwargs: Any) -> Any:
    sockname = connection.transport.get_extra_info("sockname") if connection.transport else None
    guard = _GUARDS.get(sockname[1]) if sockname else None
    if guard is not None:
        process_request = guard.wrap(process_request)
    assert _ORIGINAL_HANDSHAKE is not None
    return _ORIGINAL_HANDSHAKE(connection, process_request, *args, **kwargs)


def install(guard: Guard) -> None:
    """Check every request that arrives on ``guard.port`` from now on (before the server starts)."""
    global _ORIGINAL_HANDSHAKE
    from websockets.asyncio.server import ServerConnection

    with _LOCK:
        if _ORIGINAL_HANDSHAKE is None:
            _ORIGINAL_HANDSHAKE = ServerConnection.handshake
            ServerConnection.handshake = _guarded_handshake  # type: ignore[method-assign]
        _GUARDS[guard.port] = guard


def uninstall(guard: Guard) -> None:
    """Stop checking ``guard``'s port (its server has stopped)."""
    with _LOCK:
        if _GUARDS.get(guard.port) is guard:
            del _GUARDS[guard.port]


def guarded_server(host: str, port: int, token: str) -> tuple[Any, Guard]:
    """A viser server on ``host:port`` (a port :func:`free_port` found free) that answers only
    what its :class:`Guard` lets through, and the guard (:func:`uninstall` it after
    ``server.stop()``). A port taken meanwhile is a one-line :class:`TrustError`."""
    import viser
    from viser import _messages as viser_messages

    guard = Guard(port, own_hosts(host, port), token)
    install(guard)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints its address, without the token
            server = viser.ViserServer(host=host, port=port, verbose=False)
    except BaseException:
        uninstall(guard)
        raise
    if server.get_port() != port:  # viser moves on to the next port when one is taken
        server.stop()
        uninstall(guard)
        raise in_use(host, port)
    # A client may ask viser to publish the viewer through viser's public share service.
    with contextlib.suppress(AssertionError, KeyError):
        server._websock_server.unregister_handler(viser_messages.ShareUrlRequest)
    return server, guard
