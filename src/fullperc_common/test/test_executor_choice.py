"""executor_choice: which executor a node spins on, and the adapters that let fusion_node's callbacks run on rclpy's
EventsExecutor (message-info subscriptions, ``async`` services); a guard-condition node falls back to ``single``.

The adapter tests spin a real EventsExecutor in this process on a private domain (``ros_env``); without the
adapters the message-info callback fails with SystemError and the async service answers nothing (rclpy 7.1.5).
"""

from __future__ import annotations

import time

import pytest
from std_msgs.msg import String
from std_srvs.srv import Trigger

from fullperc_common import executor_choice
from fullperc_common.node_main import run_node


def test_choose_env_overrides_the_node_default():
    assert executor_choice.choose("fusion_node", {}) == "events"
    for node in ("margin_node", "omc_driver", "ndi_driver", "diana_state"):
        assert executor_choice.choose(node, {}) == "events", node
    assert executor_choice.choose("calibrate", {}) == "single"
    assert executor_choice.choose("fusion_node", {"FULLPERC_EXECUTOR": "single"}) == "single"
    assert executor_choice.choose("calibrate", {"FULLPERC_EXECUTOR": " Events "}) == "events"
    with pytest.raises(ValueError, match="FULLPERC_EXECUTOR='fast': must be one of events, single"):
        executor_choice.choose("fusion_node", {"FULLPERC_EXECUTOR": "fast"})


def test_bad_executor_value_exits_2_with_one_line(monkeypatch, capfd):
    monkeypatch.setenv("FULLPERC_EXECUTOR", "multi")

    def never():
        raise AssertionError("the factory must not be called")

    assert run_node(never, "unit_node", (), ["prog"]) == 2
    lines = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert lines == ["[unit_node] fatal: FULLPERC_EXECUTOR='multi': must be one of events, single"]


@pytest.fixture
def rcl(ros_env, monkeypatch):
    import rclpy
    from rclpy.context import Context

    for k, v in ros_env.items():
        monkeypatch.setenv(k, v)
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def _spin_until(ex, done, limit_s: float = 30.0) -> None:
    t0 = time.monotonic()
    while not done() and time.monotonic() - t0 < limit_s:   # liveness bound only
        ex.spin_once(timeout_sec=0.05)


def test_guard_condition_node_is_refused(rcl):
    import rclpy

    node = rclpy.create_node("guarded", context=rcl)
    assert executor_choice.events_problem(node) is None
    node.create_guard_condition(lambda: None)
    assert "guard conditions" in executor_choice.events_problem(node)
    node.destroy_node()


def test_adapted_callbacks_run_on_the_events_executor(rcl):
    """A (msg, info) subscription gets (msg, {}); an async service answers after awaiting a future that a timer
    completes later (fusion_node's ~/calibrate pattern)."""
    import rclpy
    from rclpy.callback_groups import ReentrantCallbackGroup
    from rclpy.task import Future

    node = rclpy.create_node("adapted", context=rcl)
    got: list[tuple[str, object]] = []
    node.create_subscription(String, "/adapted/in", lambda m, info: got.append((m.data, info)), 10)
    waiting: list[Future] = []

    async def on_call(_req, resp):
        f = Future()
        waiting.append(f)
        resp.success = await f
        resp.message = f"answered after {len(waiting)} wait"
        return resp

    node.create_service(Trigger, "~/call", on_call, callback_group=ReentrantCallbackGroup())
    node.create_timer(0.1, lambda: [f.set_result(True) for f in waiting if not f.done()])
    assert executor_choice.events_problem(node) is None
    executor_choice.adapt_for_events(node)
    ex = executor_choice.make_executor("events", rcl, lambda: None)
    assert type(ex).__name__ == "EventsExecutor"
    ex.add_node(node)
    client_node = rclpy.create_node("adapted_client", context=rcl)
    ex.add_node(client_node)
    pub = client_node.create_publisher(String, "/adapted/in", 10)
    client = client_node.create_client(Trigger, "/adapted/call")
    _spin_until(ex, lambda: pub.get_subscription_count() > 0 and client.service_is_ready())
    for k in range(3):
        pub.publish(String(data=str(k)))
    fut = client.call_async(Trigger.Request())
    _spin_until(ex, lambda: len(got) == 3 and fut.done())
    assert [g[0] for g in got] == ["0", "1", "2"]
    assert all(g[1] == {} for g in got)   # no message info on events
    assert fut.done() and fut.result().success and fut.result().message == "answered after 1 wait"
    ex.shutdown(timeout_sec=1.0)
    node.destroy_node()
    client_node.destroy_node()

