"""The one UDP stream backend: a :class:`~fullperc_drivers.handoff.UdpReceiver` plus a decoder.

The OMC and Diana stream backends differ only in how a datagram becomes an item (``nokov.stream``,
``diana.stream``). Every datagram is decoded on the receiver thread; a malformed one (the decoder raises
:class:`~fullperc_drivers.streams.StreamDecodeError`, and nothing else) is counted in ``decode_errors`` with its
reason in ``last_error`` and skipped. Valid items go to ``on_item`` (a ``Handoff.put`` in the nodes), which must
not raise. The stream is connectionless, so ``connected`` is always True: liveness is judged by the node's
health ladder from the arrival of items.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

from .handoff import UdpReceiver
from .streams import StreamDecodeError

T = TypeVar("T")


class UdpStreamBackend(Generic[T]):
    name = "stream"

    def __init__(self, host: str, port: int, on_item: Callable[[T], None],
                 decode: Callable[[bytes, int], T], thread_name: str = "udp-stream") -> None:
        self._on_item = on_item
        self._decode = decode
        self.decode_errors = 0
        self.last_error = ""
        self.datagrams = 0
        self._rx = UdpReceiver(host, port, self._datagram, name=thread_name)
        self.address = self._rx.address

    @property
    def connected(self) -> bool:
        return True

    def _datagram(self, data: bytes, recv_ns: int) -> None:
        self.datagrams += 1
        try:
            item = self._decode(data, recv_ns)
        except StreamDecodeError as e:
            self.decode_errors += 1
            self.last_error = str(e)
            return
        self._on_item(item)

    def close(self) -> None:
        """Stop the receiver thread (joined) and close the socket; ``on_item`` is never called afterwards."""
        self._rx.close()
