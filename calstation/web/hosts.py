"""Which ``Host`` a request may name: the defence against DNS rebinding.

A page on ``http://evil.example:8470/`` whose name is made to resolve to the station's address
is, for the browser, its own origin: it may read the station's answers and post to it. What
gives it away is the ``Host`` header, which carries the name the browser used. So the station
answers only requests whose ``Host`` is

- an address the server was started on: the ``--host`` address itself, and the local address
  the connection arrived at (for ``0.0.0.0``, each of the machine's addresses);
- ``localhost``, on a connection that arrived at a loopback address (the name cannot be
  rebound: browsers resolve it to loopback themselves);
- a name given with ``--allow-host`` (``station.plant.example``; ``*.plant.example`` for every
  name under it), as Starlette's ``TrustedHostMiddleware`` does.

Anything else is refused with HTTP 400, and so is a missing or malformed ``Host`` (not 421:
browsers retry a 421 and then show their own error page, where 400 shows the reason). The port
is not part of the check.
"""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Iterable

_HOST = re.compile(r"(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9](?:[A-Za-z0-9.-]{0,252})))"
                   r"(?::(?P<port>[0-9]{1,5}))?")

Address = ipaddress.IPv4Address | ipaddress.IPv6Address


def _address(text: str) -> Address | None:
    try:
        ip = ipaddress.ip_address(text.strip("[]"))
    except ValueError:
        return None
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        return ip.ipv4_mapped
    return ip


def is_local_host(host: str) -> bool:
    """True for a loopback bind address (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    ip = _address(host)
    return ip is not None and ip.is_loopback


def parse_host(value: str) -> tuple[str | Address, int | None] | None:
    """``Host`` header → (lower-case name or IP address, port); None when malformed."""
    m = _HOST.fullmatch(value)
    if m is None:
        return None
    port = int(m["port"]) if m["port"] else None
    if port is not None and not 0 < port < 65536:
        return None
    if m["v6"] is not None:
        ip = _address(m["v6"])
        return None if ip is None else (ip, port)
    name = m["name"].lower()
    ip = _address(name) if re.fullmatch(r"[0-9.]+", name) else None
    if ip is None and re.fullmatch(r"[0-9.]+", name):
        return None  # 999.1.1.1 is neither an address nor a name
    return (ip if ip is not None else name), port


def check_allowed_host(pattern: str) -> str:
    """An ``--allow-host`` value, lower-cased; ValueError when it is not a host name,
    ``*.name`` or an IP address."""
    text = pattern.strip().lower()
    body = text[2:] if text.startswith("*.") else text
    if not body or parse_host(body if ":" not in body or body.startswith("[")
                              else f"[{body}]") is None:
        raise ValueError(f"--allow-host {pattern!r} is not a host name, *.domain or address")
    return text


class HostPolicy:
    """Decides whether a request's ``Host`` names this station (see the module docstring)."""

    def __init__(self, bind_host: str, allow: Iterable[str] = ()) -> None:
        self.names: set[str] = set()
        self.addresses: set[Address] = set()
        self.suffixes: list[str] = []
        for entry in [bind_host, *allow]:
            text = check_allowed_host(entry)
            if text.startswith("*."):
                self.suffixes.append(text[1:])
                continue
            ip = _address(text)
            if ip is not None:
                self.addresses.add(ip)
            else:
                self.names.add(text)
        if "localhost" in self.names:
            self.addresses.update(map(ipaddress.ip_address, ("127.0.0.1", "::1")))

    def refusal(self, host_header: str | None, local_address: str | None) -> tuple[int, str] | None:
        """None if the request may be served, else (HTTP status, reason)."""
        if not host_header:
            return 400, "no Host header"
        parsed = parse_host(host_header)
        if parsed is None:
            return 400, f"malformed Host header {host_header[:100]!r}"
        host = parsed[0]
        local = _address(local_address) if local_address else None
        if isinstance(host, str):
            if host in self.names or any(host.endswith(s) for s in self.suffixes):
                return None
            if host == "localhost" and local is not None and local.is_loopback:
                return None
        elif host in self.addresses or host == local:
            return None
        return 400, (f"Host {host_header[:100]!r} is not a name of this station (DNS rebinding?); "
                     "serve with --allow-host NAME to allow it")
