"""Child process for test_node_main.py: a small node run by ``run_node`` that signals itself at a chosen moment.

  python run_node_child.py PHASE SIGNAL      PHASE: startup | spin | shutdown | thread; SIGNAL: SIGINT | SIGTERM

startup: the signal arrives inside the node's constructor, which then goes on creating a publisher and
publishing. spin: inside a 1 kHz timer callback that keeps publishing after the signal. shutdown: the first
signal as in spin, two more inside ``close()``. thread: as spin, while a device-like thread publishes in a loop
that ``close()`` does not stop (it fails once the node is destroyed). Prints ``close after N ticks``.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

from rclpy.node import Node
from std_msgs.msg import String

from fullperc_common.node_main import run_node

PHASE = sys.argv[1]
SIG = getattr(signal, sys.argv[2])


class Child(Node):
    def __init__(self) -> None:
        super().__init__("run_node_child")
        self.n = 0
        if PHASE == "startup":
            os.kill(os.getpid(), SIG)
            time.sleep(0.2)  # the handler has run by now (it runs between byte codes)
        self.pub = self.create_publisher(String, "/run_node_child/chatter", 10)
        self.pub.publish(String(data="constructed"))
        self.create_timer(0.001, self.tick)
        if PHASE == "thread":
            threading.Thread(target=self._device, name="device", daemon=False).start()

    def _device(self) -> None:
        while True:
            self.pub.publish(String(data="from the device thread"))
            time.sleep(0.0005)

    def tick(self) -> None:
        self.n += 1
        if self.n == 1:
            print(f"spinning on {type(self.executor).__name__}", flush=True)
        if self.n == 50 and PHASE != "startup":
            os.kill(os.getpid(), SIG)
            time.sleep(0.05)
            for _ in range(100):  # data still flowing in this callback after the signal
                self.pub.publish(String(data=str(self.n)))

    def close(self) -> None:
        print(f"close after {self.n} ticks", flush=True)
        if PHASE == "shutdown":
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)


if __name__ == "__main__":
    sys.exit(run_node(Child, "run_node_child", ()))
