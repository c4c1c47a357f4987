"""Where emulated and simulated devices may listen: loopback addresses only, so nothing a test
or a developer starts is reachable from the network."""

from __future__ import annotations

import ipaddress
import socket


def check_loopback(host: str, *, ipv4_only: bool = False) -> None:
    """Raise ``ValueError`` unless ``host`` is a loopback address (``localhost``, 127.0.0.0/8,
    or ::1 unless ``ipv4_only``)."""
    try:
        address = ipaddress.ip_address("127.0.0.1" if host == "localhost" else host)
        loopback = address.is_loopback and not (ipv4_only and address.version != 4)
    except ValueError:
        loopback = False
    if not loopback:
        wanted = "an IPv4 loopback address (127.x.y.z)" if ipv4_only else "a loopback address"
        raise ValueError(
            f"simulated devices are served on loopback only: host must be {wanted}; got {host!r}"
        )


def bindable(host: str, port: int) -> bool:
    """Whether a TCP server could listen on ``host``:``port`` now (nothing else holds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True
