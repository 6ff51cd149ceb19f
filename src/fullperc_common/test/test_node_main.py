"""run_node: ``--help`` without rclpy, bad configuration -> exit 2 with one line, a signal in any phase -> exit 0.

The help and configuration cases call run_node in this process (it initialises and shuts down rclpy's default
context); the signal cases run run_node_child.py, a real process that signals itself at a chosen moment.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fullperc_common import node_main
from fullperc_common.node_main import run_node, wants_help
from fullperc_common.params import ParameterError, declare

CHILD = Path(__file__).resolve().parent / "run_node_child.py"


def _never():
    raise AssertionError("the factory must not be called")


def test_wants_help_only_before_ros_args():
    assert wants_help(["prog", "--help"]) and wants_help(["-h"]) and wants_help(["x", "-h", "--ros-args"])
    assert not wants_help(["prog", "--ros-args", "-p", "a:=1", "--help"])
    assert not wants_help(["prog", "--ros-args", "--params-file", "-h"])
    assert not wants_help([])


@pytest.mark.parametrize("argv", [["prog", "--help"], ["prog", "-h", "--ros-args", "-p", "gain:=0"]])
def test_help_prints_usage_and_parameter_file_without_rclpy(argv, monkeypatch, tmp_path, capsys):
    import rclpy

    ref = tmp_path / "demo.yaml"
    ref.write_text("demo_node:\n  ros__parameters:\n    gain: 1.5   # [1/s] loop gain\n")
    looked_up = []
    monkeypatch.setattr(node_main, "share_path", lambda *parts: (looked_up.append(parts), ref)[1])
    monkeypatch.setattr(rclpy, "init", lambda *a, **k: pytest.fail("rclpy.init was called"))

    assert run_node(_never, "demo_node", (), argv, params_file=("demo_pkg", "demo.yaml")) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: ros2 run demo_pkg demo_node ")
    assert "--params-file" in out and ref.read_text() in out
    assert looked_up == [("demo_pkg", "config", "demo.yaml")]
    assert not rclpy.ok()


class _Boom(RuntimeError):
    pass


def _direct_declare():
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    node = Node("unit_node")
    node.declare_parameter("T", Parameter.Type.DOUBLE_ARRAY)  # rclpy's own exception on a wrong type
    return node


def _with_declare():
    from rclpy.node import Node

    node = Node("unit_node")
    declare(node, "gain", 1.5)
    return node


def _raises(exc):
    def factory():
        raise exc
    return factory


def _cases(tmp: Path) -> dict:
    broken = tmp / "broken.yaml"
    if tmp.is_dir():
        broken.write_text("unit_node:\n  ros__parameters:\n    gain: [1.0, 2.0\n")
    missing = tmp / "missing" / "params.yaml"
    return {
        "direct_declare_wrong_type": (["--ros-args", "-p", "T:=abc"], _direct_declare,
                                      ["'T'", "list of floats", "abc"]),
        "declare_int_for_float": (["--ros-args", "-p", "gain:=0"], _with_declare, ["'gain'", "float", "0.0"]),
        "declare_string_for_float": (["--ros-args", "-p", "gain:=abc"], _with_declare, ["'gain'", "float", "abc"]),
        "missing_params_file": (["--ros-args", "--params-file", str(missing)], _never, [str(missing)]),
        "broken_params_file": (["--ros-args", "--params-file", str(broken)], _never, [str(broken), "line"]),
        "malformed_override": (["--ros-args", "-p", "gain"], _never, ["-p gain"]),
        "unknown_ros_argument": (["--ros-args", "--no-such-flag"], _never, ["--no-such-flag"]),
        "parameter_error": ([], _raises(ParameterError("parameter 'gain' = -1 is invalid: > 0")), ["'gain'"]),
        "node_fatal_type": ([], _raises(_Boom("layout file x.yaml: field 'cameras' missing")), ["x.yaml"]),
    }


CASES = list(_cases(Path("/nonexistent-dir")))


@pytest.mark.parametrize("case", CASES)
def test_bad_configuration_exits_2_with_one_line(case, ros_env, tmp_path, capfd):
    import rclpy

    args, factory, words = _cases(tmp_path)[case]
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert run_node(factory, "unit_node", (_Boom,), ["prog", *args]) == 2
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("[unit_node] fatal: ") and all(w in lines[0] for w in words), lines[0]
    assert not rclpy.ok()  # shut down again
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # restored


@pytest.mark.parametrize("executor", ["single", "events"])
@pytest.mark.parametrize("phase, sig", [("startup", "SIGINT"), ("spin", "SIGTERM"), ("shutdown", "SIGINT"),
                                        ("thread", "SIGINT")])
def test_signal_in_any_phase_exits_0_after_close(phase, sig, executor, ros_env):
    """On both executors (the EventsExecutor installs its own signal handlers; run_node puts ours back)."""
    env = dict(ros_env, FULLPERC_EXECUTOR=executor)
    p = subprocess.run([sys.executable, str(CHILD), phase, sig], env=env, capture_output=True, text=True,
                       timeout=120)  # liveness bound
    out = p.stdout + p.stderr
    assert p.returncode == 0, out
    assert "Traceback" not in out, out
    if phase != "startup":   # the child has no guard condition: it really spun on ``executor``
        assert f"spinning on {'EventsExecutor' if executor == 'events' else 'SingleThreadedExecutor'}" in out, out
    ticks = int(p.stdout.split("close after ", 1)[1].split()[0])
    assert (ticks == 0) if phase == "startup" else (ticks >= 50), out


class _Pub:
    def __init__(self, topic: str, acked: bool, log: list, clock: list[float], takes_s: float = 0.0):
        self.topic_name, self.acked, self.log, self.clock, self.takes_s = topic, acked, log, clock, takes_s

    def wait_for_all_acked(self, timeout) -> bool:
        left = timeout.nanoseconds / 1e9
        self.log.append(("wait", self.topic_name, left))
        self.clock[0] += min(left, self.takes_s) if self.acked else left
        return self.acked


def test_wait_for_acks_shares_one_deadline_and_names_the_unacknowledged_topics():
    log: list = []
    clock = [100.0]
    node = type("N", (), {})()
    node.publishers = [_Pub("/a", True, log, clock, takes_s=1.0), _Pub("/b", False, log, clock),
                       _Pub("/c", True, log, clock)]
    late = node_main.wait_for_acks(node, 4.0, clock=lambda: clock[0])
    assert late == ["/b"]
    # /a used 1 s of the 4, /b (never acknowledged) the remaining 3, /c gets no time left but is still asked
    assert [(w, t, pytest.approx(s)) for w, t, s in log] == [("wait", "/a", 4.0), ("wait", "/b", 3.0),
                                                            ("wait", "/c", 0.0)]


def test_release_waits_for_acknowledgements_after_close_and_before_destroy(capsys):
    """A node's last samples reach a reader that was behind: the wait sits between close() (no more samples) and
    destroy_node() (the writers gone); a topic never acknowledged is named on stderr."""
    log: list = []
    clock = [0.0]

    class Node:
        publishers = [_Pub("/diana/joint_states", True, log, clock), _Pub("/diagnostics", False, log, clock)]

        def close(self):
            log.append("close")

        def destroy_node(self):
            log.append("destroy")

    assert node_main._release("unit_node", {"node": Node(), "initialised": False})
    assert [e if isinstance(e, str) else e[:2] for e in log] == [
        "close", ("wait", "/diana/joint_states"), ("wait", "/diagnostics"), "destroy"]
    err = capsys.readouterr().err
    assert "[unit_node] samples on /diagnostics still unacknowledged" in err and "/diana" not in err


def test_the_heap_is_settled_before_the_first_callback(ros_env):
    """run_node freezes what start-up left (settle_heap) before it spins: the node's first callback sees the
    permanent generation filled, so a later full collection does not walk the modules and the node again."""
    import gc

    seen: list[int] = []

    def factory():
        import rclpy

        node = rclpy.create_node("heap_node")

        def tick():
            seen.append(gc.get_freeze_count())
            signal.raise_signal(signal.SIGINT)   # run_node's handler: stop after this callback

        node.create_timer(0.01, tick)
        return node

    gc.unfreeze()
    try:
        assert run_node(factory, "heap_node", (), ["prog"]) == 0
        assert seen and seen[0] > 1000, seen
    finally:
        gc.unfreeze()


def test_settle_heap_collects_garbage_before_freezing():
    """Garbage of start-up (a reference cycle nobody holds) is collected, not frozen for the process's life."""
    import gc
    import weakref

    class Node:
        pass

    a, b = Node(), Node()
    a.other, b.other = b, a
    gone = weakref.ref(a)
    del a, b
    gc.unfreeze()
    try:
        node_main.settle_heap()
        assert gone() is None and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_the_handlers_are_restored_with_the_signals_held(ros_env, monkeypatch):
    """A SIGINT that CPython's C handler catches between ``signal.signal``'s pending-signal check and the swap
    would be run afterwards against SIG_IGN ("Signal 2 ignored due to race condition", a traceback after a
    double Ctrl-C). The window cannot be hit on purpose from Python: this pins that every swap at the end
    happens with SIGINT and SIGTERM blocked, so a signal there waits in the kernel instead."""
    real = signal.signal
    calls: list[tuple[int, bool]] = []

    def spy(s, h):
        held = signal.pthread_sigmask(signal.SIG_BLOCK, [])
        calls.append((s, {signal.SIGINT, signal.SIGTERM} <= held))
        return real(s, h)

    monkeypatch.setattr(signal, "signal", spy)
    handlers = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    assert run_node(_raises(ParameterError("parameter 'gain' = -1 is invalid: > 0")), "unit_node", (),
                    ["prog"]) == 2
    assert [s for s, _ in calls[-2:]] == [signal.SIGINT, signal.SIGTERM] and all(h for _, h in calls[-2:]), calls
    assert not signal.pthread_sigmask(signal.SIG_BLOCK, []) & {signal.SIGINT, signal.SIGTERM}  # released again
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers
