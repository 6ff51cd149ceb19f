"""The one ``main()`` every fullperc node runs: init, construct, spin, clean shutdown.

A node whose construction fails on bad configuration (a wrong parameter, a missing library or layout
file) exits with status 2 and one line naming the problem, never a traceback; Ctrl-C and an external
shutdown end it with status 0 after the node's own ``close()`` (when it has one) has released its device.
"""

from __future__ import annotations

import sys
from collections.abc import Callable


def run_node(factory: Callable[[], object], name: str, fatal: tuple[type[BaseException], ...],
             args: list[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=args)
    try:
        node = factory()
    except fatal as e:
        print(f"[{name}] fatal: {e}", file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        close = getattr(node, "close", None)
        if close is not None:
            close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
