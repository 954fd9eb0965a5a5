"""Listening for other machines, shared by the servers (``bpp serve``, ``bpp studio``): which hosts stay on this
machine, what a token must be to guard one that does not, the listening socket, and the addresses to print."""

from __future__ import annotations

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
