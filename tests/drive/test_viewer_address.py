"""The viewer serves exactly the address asked for: a taken port, a bad host and a public bind are handled."""

from __future__ import annotations

import socket
import time

import pytest

from gsavatar.drive.viewer import claim_address


def test_port_in_use_is_an_error_naming_it():
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen(1)
        port = other.getsockname()[1]
        with pytest.raises(ValueError, match=f"--port {port}: already in use"):
            claim_address("127.0.0.1", port)


def test_port_zero_picks_a_free_port():
    port = claim_address("127.0.0.1", 0)
    assert 0 < port <= 65535
    with socket.socket() as s:  # free: it binds
        s.bind(("127.0.0.1", port))


def test_unresolvable_host_fails_within_seconds():
    t = time.perf_counter()
    with pytest.raises(ValueError, match="no.such.host.invalid"):
        claim_address("no.such.host.invalid", 0, timeout=3.0)
    assert time.perf_counter() - t < 10


def test_unbindable_address_names_the_host():
    with pytest.raises(ValueError, match="192.0.2.1"):  # TEST-NET-1: never an address of this machine
        claim_address("192.0.2.1", 0)


def test_non_loopback_bind_warns_and_loopback_does_not():
    lines: list[str] = []
    claim_address("127.0.0.1", 0, warn=lines.append)
    assert lines == []
    claim_address("0.0.0.0", 0, warn=lines.append)
    assert len(lines) == 1 and "no authentication" in lines[0]


def test_bad_port_number():
    with pytest.raises(ValueError, match="65535"):
        claim_address("127.0.0.1", 70000)
