"""Whether a router is there: the address of a Zenoh endpoint, a TCP probe of it, and Zenoh's
error messages without their Rust source paths.

``ttl control`` probes the router before it opens a session (nothing listening: it says so
at once, instead of Zenoh's "Timeout!" after its connect timeout), and ``ttl inspect`` probes
the router of a run to tell a live run from one that has ended.
"""

from __future__ import annotations

import re
import socket

#: Zenoh's errors end with the Rust source line that raised them (``... Timeout! at
#: /root/.cargo/git/checkouts/zenoh-.../orchestrator.rs:388.``): of no use to an operator.
_RUST_SOURCE = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")

#: Link protocols over TCP, which :func:`listening` can probe.
TCP_PROTOCOLS = ("tcp", "tls", "ws")


def endpoint_address(endpoint: str) -> tuple[str, str, int] | None:
    """``tls/127.0.0.1:7447`` -> ``("tls", "127.0.0.1", 7447)``; ``[::1]`` loses its brackets;
    None when the endpoint is not ``protocol/host:port`` (a Unix socket, a typo)."""
    m = re.match(r"^([a-z0-9-]+)/(\[[^\]]+\]|[^:/#?\[\]]+):(\d+)(?:[#?].*)?$", str(endpoint).strip())
    if not m:
        return None
    return m.group(1), m.group(2).strip("[]"), int(m.group(3))


def listening(endpoint: str, timeout: float = 1.0) -> bool | None:
    """Whether something accepts TCP connections at ``endpoint``'s address now: True, False
    (refused, unreachable, timed out), or None when that cannot be probed (not a TCP-based
    protocol, or no ``host:port``)."""
    addr = endpoint_address(endpoint)
    if addr is None or addr[0] not in TCP_PROTOCOLS:
        return None
    _, host, port = addr
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def zenoh_error_text(exc: BaseException) -> str:
    """The message of a Zenoh error without the Rust source path it ends with."""
    return _RUST_SOURCE.sub("", str(exc)).strip()
