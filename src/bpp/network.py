"""Listening for other machines, shared by the servers (``bpp serve``, ``bpp studio``): which hosts stay on this
machine, what a token must be to guard one that does not, the listening socket, and the addresses to print."""

from __future__ import annotations

import collections
import contextlib
import errno
import ipaddress
import socket

from bpp.errors import UserError

MIN_TOKEN_CHARS = 16
TOKEN_RULE = f"at least {MIN_TOKEN_CHARS} visible ASCII characters"
"""What a token guarding a server must be (a header carries visible ASCII unchanged; shorter ones can be guessed)."""
WILDCARD_HOSTS = ("0.0.0.0", "::", "")
"""Hosts that listen on every interface of this machine."""


def is_loopback(host: str) -> bool:
    """Whether `host` is reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def strong_token(token: str) -> bool:
    """Whether `token` may guard a server that other machines reach (see :data:`TOKEN_RULE`)."""
    return len(token) >= MIN_TOKEN_CHARS and token.isascii() and token.isprintable() and " " not in token


def listen(host: str, port: int) -> socket.socket:
    """A socket listening on `host`:`port` (0: a free port), or a UserError naming the flag at fault."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except (socket.gaierror, UnicodeError) as err:
        raise UserError(f"--host {host!r}: not an address of this machine ({err})") from None
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a restart reuses the port at once
        sock.bind(address)
        sock.listen(128)
    except OSError as err:
        sock.close()
        hint = "another program uses it: choose another --port, or --port 0 for any free one"
        reason = hint if err.errno == errno.EADDRINUSE else err.strerror
        raise UserError(f"cannot listen on {host} port {port}: {reason}") from None
    return sock


def urls(scheme: str, host: str, port: int, path: str = "") -> list[str]:
    """Where clients reach a server listening on `host`:`port`: for a wildcard host, this machine's network addresses
    (what another machine opens) and then loopback (what this machine opens); else the host itself."""
    if host in WILDCARD_HOSTS:
        found = _network_addresses()
        loopback = "[::1]" if host == "::" and not found else "127.0.0.1"
        return [*(f"{scheme}://{_bracket(a)}:{port}{path}" for a in found), f"{scheme}://{loopback}:{port}{path}"]
    return [f"{scheme}://{_bracket(host)}:{port}{path}"]


def _network_addresses() -> list[str]:
    """This machine's non-loopback IPv4 addresses, the default route's first (no packet is sent to find it)."""
    found = []
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.connect(("192.0.2.1", 9))  # TEST-NET-1: connecting a UDP socket only picks the outgoing interface
        found.append(probe.getsockname()[0])
    with contextlib.suppress(OSError):
        for info in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET):
            found.append(info[4][0])
    return [a for i, a in enumerate(found) if a not in found[:i] and not ipaddress.ip_address(a).is_loopback]


def _bracket(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def client_key(host: str) -> str:
    """The address a per-client limit counts: the host itself, or for IPv6 its /64 network (one machine commonly
    holds a whole /64, and takes a new address of it at will)."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return host
    if address.version == 4:
        return str(address)
    if address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(ipaddress.ip_network(f"{address}/64", strict=False))


TOO_MANY = b"HTTP/1.1 429 Too Many Requests\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
"""The whole answer to a connection over its address's share."""


def guarded_http(header_seconds: float, per_address: int) -> type:
    """uvicorn's HTTP/1.1 protocol (h11), bounded before any route or token is read against clients that hold
    connections without finishing a request (a "slowloris"): a connection must deliver a request's headers within
    `header_seconds` of opening, or of its previous response, else it is closed; and one client address holds at most
    `per_address` connections at once, further ones are answered 429 and closed. Without these, a few hundred
    connections that send half a request's headers take every place the server has for everyone, for as long as the
    sender likes."""
    # uvicorn and h11: the studio extra
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    open_by_address: collections.Counter = collections.Counter()

    class Guarded(H11Protocol):
        _deadline = None
        _address = None

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._address = client_key(self.client[0] if self.client else "")
            open_by_address[self._address] += 1
            if open_by_address[self._address] > per_address:
                transport.write(TOO_MANY)
                transport.close()
                return
            self._arm()

        def _arm(self) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(header_seconds, self._headers_overdue)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _headers_overdue(self) -> None:
            self._deadline = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state is not h11.IDLE:  # the request's headers are in
                self._disarm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self.transport.is_closing():
                return
            if self.conn.their_state is h11.IDLE:
                self._arm()  # the next request's headers are due as the first one's were
            elif self.conn.their_state is h11.SEND_BODY:  # answered before its body was read (a refusal): no reuse
                self.transport.close()

        def _leave(self) -> None:
            self._disarm()
            if self._address is not None:
                open_by_address[self._address] -= 1
                if open_by_address[self._address] <= 0:
                    del open_by_address[self._address]
                self._address = None

        def handle_websocket_upgrade(self, event) -> None:
            self._leave()  # the connection leaves this protocol
            super().handle_websocket_upgrade(event)

        def connection_lost(self, exc) -> None:
            self._leave()
            super().connection_lost(exc)

    return Guarded
