"""A local port for a device stream of a test or the demo that no DDS participant and no kernel auto-bind takes.

Why not "bind to port 0 and take what the kernel gives": the kernel hands out its ephemeral range, and between that
pick and the driver's own bind a DDS participant can take the port -- Fast DDS binds 7400 + 250 d + {0, 1} and
7400 + 250 d + 10 + 2 i / + 11 + 2 i (participant i) for domain d (the tests' domains are
:data:`fullperc_common.testing.DOMAIN_IDS`, 1-200). A CI run lost ``omc_driver`` that way: "cannot bind UDP
127.0.0.1:41163: Address already in use", 41163 = domain 135's user unicast port of its participant 1. So the port is
drawn from offsets 200-249 of a domain's 250-port block (DDS reaches them only with ~95 participants in one domain)
below the kernel's ephemeral range (never handed out unasked), and checked free by binding it.
"""

from __future__ import annotations

import random
import socket
from pathlib import Path

__all__ = ["free_port"]

_DDS_BASE, _DDS_BLOCK = 7400, 250
_FREE_OFFSETS = range(200, 250)   # of each domain's block: no DDS port with fewer than ~95 participants


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def free_port(kind: int = socket.SOCK_DGRAM, host: str = "127.0.0.1", tries: int = 500,
              rng: random.Random | None = None) -> int:
    """A port on ``host`` (``kind``: socket.SOCK_DGRAM or SOCK_STREAM) that nothing is bound to now, outside the
    ports DDS and the kernel take by themselves (module docstring). RuntimeError if ``tries`` draws find none."""
    top = min(_ephemeral_low(), 65536)
    blocks = [b for b in range(1, 400) if _DDS_BASE + _DDS_BLOCK * b + _FREE_OFFSETS[-1] < top]
    if not blocks:
        raise RuntimeError(f"the kernel's ephemeral ports start at {top}: no DDS-free port below them")
    rng = rng or random.SystemRandom()
    for _ in range(tries):
        port = _DDS_BASE + _DDS_BLOCK * rng.choice(blocks) + rng.choice(_FREE_OFFSETS)
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        return port
    raise RuntimeError(f"no free port found in {tries} draws")
