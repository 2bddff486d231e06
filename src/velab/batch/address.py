"""The ``--scheduler`` address of ``velab fit``: checked before anything connects.

A Dask scheduler address is ``PROTOCOL://HOST:PORT``: protocol ``tcp`` or ``tls``, a host
name, an IPv4 address or a bracketed IPv6 address, and a port (Dask's default 8786 when
left out). The protocol is required (Dask itself reads a bare ``HOST:PORT`` as tcp): a bare
word must not become a connection to a host of that name. Anything else (a path, a user
name, a query, spaces) is refused with a one-line message naming the part that is wrong. Standard library only: the CLI parser uses it while ``velab --help`` builds.

velab listens on loopback unless told otherwise (docs/cli.md); connecting to a scheduler the
user names is that explicit choice, so any host is accepted here.
"""

from __future__ import annotations

import argparse
import ipaddress
import re

PROTOCOLS = ("tcp", "tls")
DEFAULT_PORT = 8786  # `dask scheduler`'s default
_HOST_NAME = re.compile(r"(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*\.?")


def parse_scheduler_address(text: str) -> str:
    """The normalised address ``proto://host:port`` of ``text``; ValueError saying what is wrong."""
    s = str(text).strip()
    if not s:
        raise ValueError("empty address")
    proto, sep, rest = s.partition("://")
    if not sep:
        raise ValueError("no protocol: write tcp://HOST:PORT or tls://HOST:PORT")
    proto = proto.lower()
    if proto not in PROTOCOLS:
        raise ValueError(f"protocol {proto!r} is not supported (use {' or '.join(p + '://' for p in PROTOCOLS)})")
    if any(c in rest for c in "/?#@ \t") or not rest.isprintable():
        raise ValueError("expected HOST:PORT after the protocol, nothing else (no path, user or query)")
    if rest.startswith("["):  # [IPv6]:port
        host, close, port = rest[1:].partition("]")
        if not close:
            raise ValueError("unclosed '[' in an IPv6 address")
        if port and not port.startswith(":"):
            raise ValueError("expected ':PORT' after ']'")
        has_port, port = bool(port), port[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"{host!r} is not an IPv6 address") from None
        shown = f"[{host}]"
    else:
        if rest.count(":") > 1:
            raise ValueError("an IPv6 address goes in brackets: tcp://[::1]:8786")
        host, colon, port = rest.partition(":")
        has_port = bool(colon)
        if not host:
            raise ValueError("no host")
        if not _HOST_NAME.fullmatch(host):
            raise ValueError(f"{host!r} is not a host name or an IP address")
        shown = host
    if not has_port:
        return f"{proto}://{shown}:{DEFAULT_PORT}"
    if not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
        raise ValueError(f"port {port!r} must be a number in 1..65535")
    return f"{proto}://{shown}:{int(port)}"


def scheduler_address(text: str) -> str:
    """An argparse ``type`` for ``--scheduler``: refused as ``argument --scheduler: ...``, exit 2."""
    try:
        return parse_scheduler_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not a Dask scheduler address ({exc}; got {text!r}, "
                                         "expected e.g. tcp://10.0.0.5:8786)") from None
