"""ExecutorWake: a device thread's items drained on the executor that spins the node, on both executors.

The drivers hand frames over with it instead of a guard condition (which rclpy 7.1's EventsExecutor cannot run):
every item reaches the drain, on the spinning thread, in order; one drain is scheduled at a time; what came before
the node was spinning is drained by ``catch_up``."""

from __future__ import annotations

import threading

import pytest

from fullperc_common.testing import wait_for
from fullperc_drivers.handoff import ExecutorWake, Handoff


@pytest.mark.parametrize("kind", ["events", "single"])
def test_items_from_a_thread_are_drained_on_the_spinning_thread_in_order(rclpy_context, kind):
    import rclpy

    from fullperc_common.executor_choice import make_executor

    node = rclpy.create_node(f"wake_{kind}", context=rclpy_context)
    got: list[tuple[int, bool]] = []
    drains = []
    spinner: list[int] = []

    def drain() -> None:
        drains.append(1)
        got.extend((i, threading.get_ident() == spinner[0]) for i in h.drain())

    wake = ExecutorWake(node, drain)
    h: Handoff[int] = Handoff(maxlen=10_000, notify=wake)
    h.put(-1)   # before the node spins: nothing scheduled (no executor); the item waits in the queue
    assert node.executor is None and h.drain() == [-1]
    ex = make_executor(kind, rclpy_context, lambda: None)
    ex.add_node(node)
    stop = threading.Event()

    def spin() -> None:
        spinner.append(threading.get_ident())
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.05)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    wait_for(lambda: spinner, 10, what="the spinning thread")
    producer = threading.Thread(target=lambda: [h.put(i) for i in range(2000)])
    producer.start()
    producer.join()
    try:
        wait_for(lambda: len(got) == 2000, 30, what="every item drained", detail=lambda: len(got))
    finally:
        stop.set()
        th.join(5)
        ex.shutdown()
        node.destroy_node()
    assert [i for i, _ in got] == list(range(2000))
    assert all(on_spinner for _, on_spinner in got)
    assert len(drains) <= 2000   # a put while a drain is scheduled schedules none


def test_catch_up_drains_only_when_no_drain_is_scheduled():
    class FakeExecutor:
        def __init__(self) -> None:
            self.tasks = []

        def create_task(self, fn):
            self.tasks.append(fn)

    class FakeNode:
        executor = None

    node, calls = FakeNode(), []
    wake = ExecutorWake(node, lambda: calls.append(1))
    wake()                       # not spinning: nothing scheduled
    wake.catch_up()              # the timer's catch-up drains
    assert calls == [1]
    node.executor = ex = FakeExecutor()
    wake()
    wake()                       # one drain at a time
    assert len(ex.tasks) == 1
    wake.catch_up()              # scheduled: left to it
    assert calls == [1]
    ex.tasks.pop()()
    assert calls == [1, 1]
    wake()
    assert len(ex.tasks) == 1    # scheduled again once the previous one ran
