"""`echo`, `pub` and `call`: the parts of `ros2 topic echo/pub` and `ros2 service call` we need, for systems without
the ros2 CLI.

The PyPI wheels ship no ros2cli and no rosidl_runtime_py, so this carries the small pieces:
type lookup by name (:func:`.types.get_message`, the one the recorder and the player use), message <->
plain dict, and a wait for discovery before publishing. It lives in :mod:`fullperc_eval.bag` for that shared
type lookup.

    echo /fullperc/tool/pose [--type geometry_msgs/msg/PoseStamped] [--count N] [--timeout S]
    pub  /topic fullperc_msgs/msg/TrackingQuality '{"body": "tool", "visible": true}' [--rate HZ] [--count N]
    call /fusion_node/calibrate std_srvs/srv/Trigger ['{}'] [--timeout S]

`call` waits for the service, sends one request (fields as JSON/YAML, default all zero) and prints the response
as one JSON object; status 0 once a response came (whatever it says: ``{"success": false, ...}`` is an answer),
1 when no server appeared or it did not answer within ``--timeout``, 2 for a bad type or request.

`echo` prints one JSON object per message on stdout (machine-readable, for scripts and tests). When the reader
of a pipe goes away (``echo /topic | head -3``), it stops quietly with status 141, as a coreutils program killed
by SIGPIPE does, instead of a BrokenPipeError traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

from .errors import BagError
from .types import get_message

SCALARS = (bool, int, float, str)


def to_dict(msg: Any) -> Any:
    """Plain Python structure of a ROS message (nested dicts, lists, numbers, strings)."""
    if hasattr(msg, "get_fields_and_field_types"):
        return {name: to_dict(getattr(msg, name)) for name in msg.get_fields_and_field_types()}
    if isinstance(msg, bytes):
        return list(msg)
    if isinstance(msg, SCALARS) or msg is None:
        return msg
    try:
        return [to_dict(v) for v in msg]  # sequences, arrays, numpy arrays
    except TypeError:
        return str(msg)


def fill(msg: Any, values: dict) -> Any:
    """Set the fields of ``msg`` from a nested dict; unknown fields raise ValueError."""
    fields = msg.get_fields_and_field_types()
    for key, val in values.items():
        if key not in fields:
            raise ValueError(f"{type(msg).__name__} has no field {key!r} (fields: {', '.join(fields)})")
        cur = getattr(msg, key)
        if isinstance(val, dict) and hasattr(cur, "get_fields_and_field_types"):
            fill(cur, val)
        else:
            setattr(msg, key, val)
    return msg


def _topic_type(node, topic: str, timeout: float) -> str | None:
    end = time.monotonic() + timeout
    import rclpy

    while time.monotonic() < end:
        for name, types in node.get_topic_names_and_types():
            if name == topic and types:
                return types[0]
        rclpy.spin_once(node, timeout_sec=0.1)
    return None


def echo_main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="echo", description="Print messages of a topic as JSON lines.")
    ap.add_argument("topic")
    ap.add_argument("--type", help="message type (pkg/msg/Type); discovered from the graph if omitted")
    ap.add_argument("--count", type=int, default=0, help="exit after N messages (0 = run until Ctrl-C)")
    ap.add_argument("--timeout", type=float, default=0.0, help="exit with status 1 after S seconds (0 = never)")
    ap.add_argument("--best-effort", action="store_true", help="subscribe with BEST_EFFORT reliability")
    ap.add_argument("--transient-local", action="store_true", help="subscribe with TRANSIENT_LOCAL durability")
    args = ap.parse_args(argv)

    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node("fullperc_echo")
    start = time.monotonic()
    try:
        type_name = args.type or _topic_type(node, args.topic, args.timeout or 1e9)
        if type_name is None:
            print(f"echo: no publisher of {args.topic} appeared within {args.timeout} s", file=sys.stderr)
            return 1
        cls = get_message(type_name)
        qos = QoSProfile(depth=100)
        if args.best_effort:
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        if args.transient_local:
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        seen = 0

        def on_msg(msg) -> None:
            nonlocal seen
            seen += 1
            print(json.dumps(to_dict(msg)), flush=True)

        node.create_subscription(cls, args.topic, on_msg, qos)
        while rclpy.ok() and (args.count == 0 or seen < args.count):
            if args.timeout and time.monotonic() - start > args.timeout:
                print(f"echo: timed out after {args.timeout} s with {seen} messages", file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.1)
        return 0
    except (ValueError, BagError) as e:
        print(f"echo: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:
        return stdout_closed()
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


EXIT_SIGPIPE = 128 + 13  # the status a shell reports for a program killed by SIGPIPE (`yes | head -1`)


def stdout_closed() -> int:
    """The reader of stdout went away: stop quietly, like coreutils (status 141, no message).

    Python ignores SIGPIPE, so the write raised BrokenPipeError; stdout is pointed at /dev/null so that the
    interpreter's final flush of what is still buffered does not raise (and print) it again.
    """
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass
    return EXIT_SIGPIPE


def pub_main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="pub", description="Publish a message given as JSON/YAML.")
    ap.add_argument("topic")
    ap.add_argument("type", help="message type, e.g. fullperc_msgs/msg/TrackingQuality")
    ap.add_argument("values", nargs="?", default="{}", help="field values as JSON or YAML")
    ap.add_argument("--rate", type=float, default=1.0, help="Hz")
    ap.add_argument("--count", type=int, default=0, help="publish N times then exit (0 = until Ctrl-C)")
    ap.add_argument("--wait-subscribers", type=int, default=0,
                    help="wait until this many subscriptions matched before publishing")
    args = ap.parse_args(argv)

    import rclpy
    import yaml

    try:
        cls = get_message(args.type)
        msg = _filled(cls(), args.values)
    except (ValueError, TypeError, AssertionError, BagError, yaml.YAMLError) as e:
        print(f"pub: {e}", file=sys.stderr)
        return 2

    rclpy.init()
    node = rclpy.create_node("fullperc_pub")
    pub = node.create_publisher(cls, args.topic, 10)
    try:
        while rclpy.ok() and pub.get_subscription_count() < args.wait_subscribers:
            rclpy.spin_once(node, timeout_sec=0.05)
        sent = 0
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        while rclpy.ok() and (args.count == 0 or sent < args.count):
            pub.publish(msg)
            sent += 1
            rclpy.spin_once(node, timeout_sec=period)
        # give reliable delivery a moment before the participant disappears
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        return 0
    except KeyboardInterrupt:
        return 0
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


def _filled(obj, text: str):
    """``obj`` (a message or a service request) with the fields ``text`` gives as a JSON / YAML mapping."""
    import yaml

    values = yaml.safe_load(text) or {}
    if not isinstance(values, dict):
        raise ValueError("values must be a mapping")
    return fill(obj, values)


def get_service(srvtype: str):
    """Python class of 'pkg/srv/Name' (it has ``Request`` and ``Response``); BagError naming the type otherwise."""
    cls = get_message(srvtype)
    if not (hasattr(cls, "Request") and hasattr(cls, "Response")):
        raise BagError(f"{srvtype!r} is not a service type (expected 'pkg/srv/Name')")
    return cls


def call_main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="call", description="Call a service once and print its response as JSON.")
    ap.add_argument("service", help="service name, e.g. /fusion_node/calibrate")
    ap.add_argument("type", help="service type, e.g. std_srvs/srv/Trigger")
    ap.add_argument("values", nargs="?", default="{}", help="request fields as JSON or YAML")
    ap.add_argument("--timeout", type=float, default=0.0,
                    help="exit with status 1 when no server appeared or it did not answer within S seconds "
                         "(0 = wait; a calibration takes as long as its collection)")
    args = ap.parse_args(argv)

    import rclpy
    import yaml

    try:
        srv = get_service(args.type)
        request = _filled(srv.Request(), args.values)
    except (ValueError, TypeError, AssertionError, BagError, yaml.YAMLError) as e:
        print(f"call: {e}", file=sys.stderr)
        return 2

    rclpy.init()
    node = rclpy.create_node("fullperc_call")
    client = node.create_client(srv, args.service)
    end = time.monotonic() + args.timeout if args.timeout > 0 else None
    try:
        while not client.service_is_ready():
            if end is not None and time.monotonic() > end:
                print(f"call: no server of {args.service} appeared within {args.timeout} s", file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.1)
        future = client.call_async(request)
        while not future.done():
            if end is not None and time.monotonic() > end:
                print(f"call: {args.service} did not answer within {args.timeout} s", file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.1)
        print(json.dumps(to_dict(future.result())), flush=True)
        return 0
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return stdout_closed()
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


if __name__ == "__main__":
    sys.exit(echo_main())
