"""Which rclpy executor a node spins on: ``single`` (SingleThreadedExecutor) or ``events`` (EventsExecutor).

Why a choice: rclpy's SingleThreadedExecutor rebuilds a wait set in Python and wraps every ready callback in a
Task on each ``spin_once`` (the ``exec:`` rows of ``bench/profile_node.py``); rclpy 7.1's
``rclpy.experimental.EventsExecutor`` queues rmw's "new data" events in C++ and calls the Python callback
directly, so a node fed at hundreds of messages per second spends less CPU outside its own callbacks.

Why not everywhere: rclpy 7.1's EventsExecutor (Jazzy) cannot do three things our nodes use (tried in
``test/test_executor_choice.py``), and a later one changes signal handling:

* guard conditions (``Node.create_guard_condition``; our nodes use none: the drivers hand device-thread items
  over with ``Executor.create_task``, ``fullperc_drivers.handoff.ExecutorWake``): it refuses the node. Such a node
  runs on ``single`` (one line on stderr says so);
* subscription callbacks taking ``(msg, info)``: it fails with ``SystemError``. :func:`adapt_for_events` wraps
  them so they get ``(msg, {})`` -- the message info (``received_timestamp``) is not available on ``events``;
* ``async def`` service callbacks (``fusion_node``'s ``~/calibrate`` awaits the collection): it sends the
  coroutine object as the response and fails. :func:`adapt_for_events` runs them as rclpy Tasks stepped by a
  20 ms timer and sends the response (with the request's header) when the coroutine returns;
* SIGINT/SIGTERM: the installed rclpy 7.1.5 leaves the process's handlers alone (checked with sigaction), but
  the EventsExecutor of later rclpy releases installs its own (asio) in its constructor, resets them to the
  default action when destroyed, and shuts the context down from ``spin_once`` -- the asynchronous shutdown
  node_main exists to avoid. :func:`make_executor` and :func:`drop_executor` therefore put the caller's handlers
  back after both, with the signals held meanwhile (nothing is lost), so an rclpy update cannot undo it.

Choice: ``FULLPERC_EXECUTOR=events|single`` in the environment overrides the node's default
(:data:`DEFAULT_EVENTS`: the nodes whose system tests pass on ``events``).
"""

from __future__ import annotations

import contextlib
import inspect
import os
import signal
from collections.abc import Callable, Iterator

ENV = "FULLPERC_EXECUTOR"
CHOICES = ("events", "single")
# Nodes that spin on ``events`` unless FULLPERC_EXECUTOR says otherwise: their system tests pass on it and the
# gain is measured (docs/performance.md "The executor"). Every other node: ``single``.
DEFAULT_EVENTS = frozenset({"fusion_node", "margin_node", "omc_driver", "ndi_driver", "diana_state"})
TASK_PERIOD_S = 0.02   # how often a pending ``async`` service callback is resumed on ``events``


def choose(name: str, environ: dict[str, str] | None = None) -> str:
    """The executor kind for node ``name``: the environment's ``FULLPERC_EXECUTOR``, else the node's default.

    Raises ValueError (one line) for a value that is not one of :data:`CHOICES`."""
    env = os.environ if environ is None else environ
    value = env.get(ENV, "").strip().lower()
    if not value:
        return "events" if name in DEFAULT_EVENTS else "single"
    if value not in CHOICES:
        raise ValueError(f"{ENV}={env.get(ENV)!r}: must be one of {', '.join(CHOICES)}")
    return value


def events_problem(node) -> str | None:
    """Why ``node`` cannot spin on the EventsExecutor (one line), or None."""
    if list(node.guards):
        return "it uses guard conditions, which rclpy's EventsExecutor does not support"
    for w in node.waitables:
        with contextlib.suppress(Exception):
            if w.get_num_entities().num_guard_conditions:
                return f"its waitable {type(w).__name__} uses guard conditions"
    for kind, entities in (("subscription", node.subscriptions), ("timer", node.timers)):
        for e in entities:
            if inspect.iscoroutinefunction(e.callback):
                return f"a {kind} callback is a coroutine, which rclpy's EventsExecutor cannot await"
    return None


@contextlib.contextmanager
def signals_blocked() -> Iterator[None]:
    """Hold SIGINT/SIGTERM (pending, not lost) while handlers are swapped; no-op outside the main thread."""
    sigs = {signal.SIGINT, signal.SIGTERM}
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    except (AttributeError, OSError, ValueError):
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def make_executor(kind: str, context, reinstall_handlers: Callable[[], None]):
    """A new executor of ``kind`` on ``context``. For ``events`` the caller's SIGINT/SIGTERM handlers are put
    back (``reinstall_handlers``) over the ones the EventsExecutor installs."""
    if kind == "single":
        from rclpy.executors import SingleThreadedExecutor

        return SingleThreadedExecutor(context=context)
    from rclpy.experimental import EventsExecutor

    with signals_blocked():
        ex = EventsExecutor(context=context)
        reinstall_handlers()
    return ex


def drop_executor(box: list, reinstall_handlers: Callable[[], None]) -> None:
    """Release the executor in ``box`` (the caller's last reference, cleared here); an EventsExecutor resets
    SIGINT/SIGTERM to the default action when it is destroyed (asio), so the caller's handlers are put back, with
    the signals held meanwhile."""
    with signals_blocked():
        box.clear()
        reinstall_handlers()


class _Deferred:
    """The answer of an ``async`` service callback still running; sent when its Task is done."""

    def __init__(self, task) -> None:
        self.task = task
        self.header = None
        self.sent = False


class _EventsAdapter:
    """Per node: the wrapped callbacks and the timer that resumes pending ``async`` service callbacks."""

    def __init__(self, node) -> None:
        self.node = node
        self.pending: list[tuple[_Deferred, Callable]] = []

    def wrap_info(self, sub) -> None:
        cb = sub.callback
        sub.callback = lambda msg: cb(msg, {})   # one argument: MessageOnly

    def wrap_async_service(self, srv) -> None:
        from rclpy.task import Task

        cb, send = srv.callback, srv.send_response

        def start(request, response):
            task = Task(cb, (request, response))
            task()   # runs up to its first await (or to the end)
            return _Deferred(task)

        def send_response(response, header) -> None:
            if not isinstance(response, _Deferred):
                send(response, header)
                return
            response.header = header
            self.pending.append((response, send))
            self.step()

        srv.callback = start
        srv.send_response = send_response   # the EventsExecutor looks it up on the instance

    def step(self) -> None:
        """Resume every pending ``async`` service callback once; answer the finished ones."""
        keep = []
        for d, send in self.pending:
            d.task()
            if not d.task.done():
                keep.append((d, send))
                continue
            exc = d.task.exception()
            if exc is not None:
                raise exc
            send(d.task.result(), d.header)
        self.pending = keep


def adapt_subscription(node, sub) -> None:
    """A subscription made after :func:`adapt_for_events` (a node remaking one at run time): wrapped the same way if
    the node spins on the EventsExecutor, else left alone."""
    ad = getattr(node, "_fullperc_events_adapter", None)
    if ad is not None and getattr(sub, "_callback_type", None) is not None \
            and sub._callback_type.name == "WithMessageInfo":
        ad.wrap_info(sub)


def adapt_for_events(node) -> None:
    """Make ``node``'s callbacks work on rclpy 7.1's EventsExecutor (module docstring); call before add_node."""
    ad = _EventsAdapter(node)
    for sub in list(node.subscriptions):
        if getattr(sub, "_callback_type", None) is not None and sub._callback_type.name == "WithMessageInfo":
            ad.wrap_info(sub)
    asyncs = [s for s in node.services if inspect.iscoroutinefunction(s.callback)]
    for srv in asyncs:
        ad.wrap_async_service(srv)
    if asyncs:
        node.create_timer(TASK_PERIOD_S, ad.step)
    node._fullperc_events_adapter = ad   # keeps the adapter alive with the node
