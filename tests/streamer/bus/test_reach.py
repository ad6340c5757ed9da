"""Unit tests of :mod:`streamer.bus.reach`: endpoint addresses, a TCP probe, Zenoh's error text."""

import socket

import pytest

from streamer.bus.reach import endpoint_address, listening, zenoh_error_text


@pytest.mark.parametrize(
    "endpoint, address",
    [
        ("tls/127.0.0.1:7447", ("tls", "127.0.0.1", 7447)),
        (" tcp/localhost:80 ", ("tcp", "localhost", 80)),
        ("tcp/[::1]:7447", ("tcp", "::1", 7447)),
        ("tls/10.0.0.5:7447#iface=eth0", ("tls", "10.0.0.5", 7447)),
        ("unixsock-stream//tmp/zenoh.sock", None),
        ("127.0.0.1:7447", None),
        ("tcp/127.0.0.1", None),
    ],
)
def test_endpoint_address(endpoint, address):
    assert endpoint_address(endpoint) == address


def test_listening_probes_a_real_socket():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        port = server.getsockname()[1]
        assert listening(f"tcp/127.0.0.1:{port}") is True
        assert listening(f"tls/127.0.0.1:{port}") is True
    # the port is closed now: refused
    assert listening(f"tcp/127.0.0.1:{port}", timeout=0.5) is False
    # not TCP-based, or no host:port: cannot be probed
    assert listening(f"udp/127.0.0.1:{port}") is None
    assert listening("unixsock-stream//tmp/x.sock") is None


def test_zenoh_error_text_drops_the_rust_source():
    exc = RuntimeError(
        "Unable to connect to tls/127.0.0.1:7447! Timeout! at /root/.cargo/git/zenoh/orchestrator.rs:388."
    )
    assert zenoh_error_text(exc) == "Unable to connect to tls/127.0.0.1:7447! Timeout!"
    assert zenoh_error_text(ValueError(" plain ")) == "plain"
