"""fullperc_common.ports.free_port: a device-stream port that no DDS participant of the tests' domains and no kernel
auto-bind takes (the module docstring says why: a CI run lost omc_driver's bind to a DDS participant)."""

from __future__ import annotations

import socket

import pytest

from fullperc_common.ports import _ephemeral_low, free_port
from fullperc_common.testing import DOMAIN_IDS


def _dds_ports(participants: int = 60) -> set[int]:
    """Every port Fast DDS binds on the tests' domains with up to ``participants`` participants per domain."""
    out = set()
    for d in DOMAIN_IDS:
        base = 7400 + 250 * d
        out |= {base, base + 1}
        for i in range(participants):
            out |= {base + 10 + 2 * i, base + 11 + 2 * i}
    return out


@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM])
def test_free_port_is_bindable_and_outside_dds_and_the_ephemeral_range(kind):
    dds = _dds_ports()
    low = _ephemeral_low()
    for _ in range(200):
        port = free_port(kind)
        assert port not in dds and port < low and (port - 7400) % 250 >= 200
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", port))   # free when drawn


def test_a_bound_port_is_not_handed_out():
    """A draw that lands on a bound port draws again: with the first draw forced onto a port held here, the port
    returned is another one; with every draw on it, RuntimeError."""
    import random

    port = free_port()
    block, offset = (port - 7400) // 250, (port - 7400) % 250

    class Forced(random.Random):   # the first choice of a block and of an offset: the held port's
        def __init__(self, first: int) -> None:
            super().__init__(0)
            self.left = first

        def choice(self, seq):
            if self.left > 0:
                self.left -= 1
                return block if len(seq) > 50 else offset
            return super().choice(seq)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))
        assert free_port(rng=Forced(2)) != port
        with pytest.raises(RuntimeError, match="no free port"):
            free_port(tries=5, rng=Forced(10))
