"""The one ``main()`` every fullperc node runs: help, init, construct, spin, clean shutdown.

Exit status, for every node:

* ``--help`` / ``-h`` (before ``--ros-args``): a usage line and the node's commented parameter file (every
  parameter with unit and default) on stdout, status 0. rclpy is not initialised and the node not constructed,
  so nothing is bound or opened.
* Bad configuration: status 2 and ONE line ``[<node>] fatal: ...`` on stderr naming the parameter or the file,
  never a traceback. That covers a missing, unreadable or broken ``--params-file``, a malformed ``-p``, unknown
  ROS arguments, a parameter of the wrong type (rclpy's ParameterException, also when a node calls
  ``declare_parameter`` itself), :class:`~fullperc_common.params.ParameterError`, and the node's own ``fatal``
  exception types (missing library, layout error, port in use ...).
* SIGINT / SIGTERM: status 0 in every phase (during rclpy init and construction, while data flows, during
  shutdown), after the node's own ``close()`` (when it has one) has stopped its device threads. A signal
  during construction does not interrupt the constructor: the node is closed as soon as it returns.
  ``close()`` raising gives status 1 with its traceback (a bug in the node, not a way to stop). Before the node
  is destroyed, every publisher's samples get up to :data:`SHUTDOWN_ACK_WAIT_S` (in all) to be acknowledged by
  the readers (:func:`wait_for_acks`); topics still unacknowledged then are named in one line on stderr.

Why our own signal handling: rclpy's default handlers shut the context down asynchronously, from the signal,
while callbacks may be running; a callback (or a device thread) that then publishes raises ``RCLError: context
not valid`` and the node dies with status 1 and a traceback. Here rclpy is initialised with
``SignalHandlerOptions.NO``; our handler only sets a flag (and wakes the executor), the executor spins in short
slices until the flag is set, and then, outside any callback, the node is closed, destroyed and rclpy shut
down, in that order. Further signals during shutdown only set the flag again, and once run_node returns as a
process's main (``args`` None) SIGINT/SIGTERM are ignored while the interpreter finalises. Exceptions that
threads raise after the stop was requested (a device thread publishing into the closing node) are reported in
one line, not as a traceback. A signal that arrives while Python is still importing the node's module (before
``main()`` runs) is outside this function: there Python's defaults apply.

Heap: once the node is built, start-up's objects are frozen out of the garbage collector's full collections
(:func:`settle_heap`), which would otherwise stall every callback for tens of milliseconds now and then.

Executor: ``single`` (rclpy's SingleThreadedExecutor) or ``events`` (rclpy.experimental.EventsExecutor, less
Python per message), chosen by :mod:`~fullperc_common.executor_choice`: ``FULLPERC_EXECUTOR=events|single``, else
the node's default (``events`` for fusion_node). A bad value is bad configuration (status 2). A node that
``events`` cannot run (guard conditions) spins on ``single`` with one line on stderr. Everything above holds for
both: the EventsExecutor's own signal handlers are replaced by ours.
"""

from __future__ import annotations

import contextlib
import gc
import os
import re
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from . import executor_choice
from .params import ParameterError, parameter_exception_message
from .share import share_path

# The Python-level signal handler runs in the main thread between byte codes, i.e. when a wait returns; this
# bounds how long a stop request can wait (the handler also wakes the executor, so it is usually immediate).
SPIN_SLICE_S = 0.1
# A reliable writer re-sends a sample a reader missed (a full socket buffer on a busy machine) only after its next
# heartbeat, every 3 s with Fast DDS's defaults, and only while the writer exists: a node that exits at once loses
# the tail of its stream to a reader that was behind (seen: a recorder without the last 0.74 s of the joint states
# when the demo graph stopped its drivers). Shutdown waits for the acknowledgements up to this long in all; the
# supervisor's grace before SIGTERM (5 s) is longer.
SHUTDOWN_ACK_WAIT_S = 4.0
HELP_FLAGS = ("-h", "--help")


def wants_help(argv: Sequence[str]) -> bool:
    """True when ``-h`` or ``--help`` comes before ``--ros-args`` (after it, the arguments are ROS's)."""
    for a in argv:
        if a == "--ros-args":
            return False
        if a in HELP_FLAGS:
            return True
    return False


def help_text(name: str, package: str, params_file: tuple[str, str] | None) -> str:
    """Usage line plus the node's parameter file (the commented YAML is the parameter reference)."""
    usage = f"usage: ros2 run {package} {name} [--ros-args -p name:=value | --params-file FILE]\n"
    if params_file is None:
        return usage + "\nNo parameter file is registered for this node; see docs/nodes.md.\n"
    try:
        path = share_path(params_file[0], "config", params_file[1])
        text = path.read_text()
    except OSError as e:
        return usage + f"\nParameter reference not available: {e}\n"
    return (usage + f"\nParameters with units and defaults, from {path}\n"
            "(pass this file or an edited copy with --params-file, or single values with -p name:=value):\n\n"
            + text + ("" if text.endswith("\n") else "\n"))


def params_files(argv: Sequence[str]) -> list[str]:
    """The ``--params-file`` arguments inside ``--ros-args`` sections."""
    out, in_ros = [], False
    it = iter(argv)
    for a in it:
        if a == "--ros-args":
            in_ros = True
        elif a == "--":
            in_ros = False
        elif in_ros and a == "--params-file":
            out.append(next(it, ""))
    return out


def check_params_file(path: str) -> str | None:
    """Why ``path`` cannot be used as a parameter file (one line), or None. rcl's own parser has the last word."""
    if not path:
        return "--params-file needs a file name"
    p = Path(path)
    if not p.exists():
        return f"parameter file '{path}' does not exist"
    if not p.is_file():
        return f"parameter file '{path}' is not a file"
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as e:
        return f"parameter file '{path}' cannot be read: {e}"
    try:
        import yaml
    except ImportError:  # pragma: no cover - PyYAML comes with ROS; rcl still checks the file
        return None
    try:
        yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        return f"parameter file '{path}' is not valid YAML: {where}{' '.join(str(problem).split())}"
    return None


def init_error_message(e: BaseException) -> str:
    """One line for an exception of ``rclpy.init`` (RCLError with rcl's message, UnknownROSArgsError)."""
    if type(e).__name__ == "UnknownROSArgsError":
        return f"unknown ROS arguments {e} (usage: --ros-args -p name:=value | --params-file FILE | -r from:=to)"
    text = " ".join(str(e).split())
    text = re.sub(r", at [^,]*?:\d+", "", text)  # rcl's source locations
    text = text.removeprefix("failed to initialize rcl: ")
    m = re.search(r"Couldn't parse params file: '--params-file (.*?)'\. Error: (.*)", text)
    if m:
        return f"parameter file '{m[1]}' rejected by rcl: {m[2]}"
    m = re.search(r"Couldn't parse parameter override rule: '(.*?)'\. Error: (.*)", text)
    if m:
        return f"cannot parse the parameter override '{m[1]}' (write -p name:=value): {m[2]}"
    return f"cannot initialise ROS: {text}"


def _fatal(name: str, msg: str) -> int:
    print(f"[{name}] fatal: {' '.join(msg.split())}", file=sys.stderr, flush=True)
    return 2


@contextlib.contextmanager
def _stderr_held() -> Iterator[dict]:
    """Hold what C code writes to fd 2 (rcl logs its own line when init fails); the caller decides to replay it."""
    held: dict = {"data": b""}
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield held
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield held
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            held["data"] = tmp.read()


class _StopRequest:
    """Signal handler: remember the request and wake the executor; never raises, safe to receive repeatedly."""

    def __init__(self) -> None:
        self.requested = False
        self.signals: list[int] = []
        self.executor = None
        self.install: Callable[[], None] = lambda: None   # (re-)installs this handler; run_node sets it

    def __call__(self, signum, _frame) -> None:
        self.requested = True
        self.signals.append(signum)
        ex = self.executor
        if ex is not None:
            with contextlib.suppress(Exception):
                ex.wake()  # triggers a guard condition: returns the executor from its wait at once


def _describe(e: BaseException) -> str:
    from rclpy.exceptions import ParameterException

    if isinstance(e, ParameterException):
        return parameter_exception_message(e)
    text = str(e).strip()
    return text if text else type(e).__name__


def run_node(factory: Callable[[], object], name: str, fatal: tuple[type[BaseException], ...] = (),
             args: list[str] | None = None, *, params_file: tuple[str, str] | None = None) -> int:
    """Run the node built by ``factory`` until SIGINT/SIGTERM or an external shutdown; return the exit status.

    ``fatal``: the node's own exception types that mean bad configuration (exit 2, one line);
    ParameterError and rclpy's parameter and name exceptions are always fatal. ``args``: as for
    ``rclpy.init`` (None: ``sys.argv``). ``params_file``: (package, file name in the package's ``config/``)
    printed by ``--help``.
    """
    argv = list(sys.argv[1:] if args is None else args)
    if wants_help(argv):
        package = params_file[0] if params_file else getattr(factory, "__module__", "?").split(".")[0]
        sys.stdout.write(help_text(name, package, params_file))
        sys.stdout.flush()
        return 0
    for f in params_files(argv):
        problem = check_params_file(f)
        if problem:
            return _fatal(name, problem)

    try:
        kind = executor_choice.choose(name)
    except ValueError as e:
        return _fatal(name, str(e))

    stop = _StopRequest()
    main_thread = threading.current_thread() is threading.main_thread()
    old_handlers = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)} if main_thread else {}
    if main_thread:   # the EventsExecutor replaces our handlers when it is created and destroyed: put them back
        def install() -> None:
            for s in (signal.SIGINT, signal.SIGTERM):
                signal.signal(s, stop)

        stop.install = install
    old_hook = threading.excepthook

    def thread_hook(a) -> None:
        if stop.requested:  # a device thread failing against the closing node: one line, no traceback
            print(f"[{name}] after the stop request, thread {getattr(a.thread, 'name', '?')} ended with "
                  f"{a.exc_type.__name__}: {a.exc_value}", file=sys.stderr, flush=True)
        else:
            old_hook(a)

    threading.excepthook = thread_hook
    held: dict = {"node": None, "initialised": False}
    try:
        status = _start_and_spin(factory, name, fatal, args, stop, held, kind)
    finally:
        stop.requested = True  # from here on a signal only sets the flag again; thread errors are one line
        close_ok = _release(name, held)
        # As a process's main (args None: a console script) the process ends next: ignore SIGINT/SIGTERM from
        # here on (the interpreter resets Python-level handlers to SIG_DFL while it finalises, so a second
        # Ctrl-C there would kill the process with -SIGINT; SIG_IGN survives that), and keep the thread hook
        # while device threads may still be ending. Called in-process with explicit args (tests): restore both.
        # The signals are held while the handlers change: a SIGINT caught by CPython's C handler just before
        # the swap would otherwise be run after it against SIG_IGN ("Signal 2 ignored due to race
        # condition", a traceback on stderr); held, it is discarded by the kernel under SIG_IGN.
        with executor_choice.signals_blocked():
            if args is None:
                for s in old_handlers:
                    signal.signal(s, signal.SIG_IGN)
            else:
                for s, h in old_handlers.items():
                    signal.signal(s, h)
            if threading.active_count() == 1:
                threading.excepthook = old_hook
    return status if close_ok else 1


def _start_and_spin(factory, name: str, fatal: tuple[type[BaseException], ...], args, stop: _StopRequest,
                    held: dict, kind: str = "single") -> int:
    import rclpy
    from rclpy.exceptions import NameValidationException, ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    try:
        with _stderr_held() as err:
            rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as e:  # noqa: BLE001 - RCLError, UnknownROSArgsError, ...: all bad arguments
        return _fatal(name, init_error_message(e))
    held["initialised"] = True
    if err["data"]:
        os.write(2, err["data"])  # init succeeded: what it wrote was not about a failure, show it
    context = rclpy.get_default_context()
    if stop.requested:
        return 0
    try:
        held["node"] = node = factory()
    except (ParameterError, ParameterException, NameValidationException, *fatal) as e:
        return _fatal(name, _describe(e))
    if stop.requested:
        return 0
    if kind == "events":
        problem = executor_choice.events_problem(node)
        if problem:
            print(f"[{name}] executor 'events' not usable ({problem}): spinning on 'single'", file=sys.stderr,
                  flush=True)
            kind = "single"
        else:
            executor_choice.adapt_for_events(node)
    settle_heap()
    executor = executor_choice.make_executor(kind, context, stop.install)
    executor.add_node(node)
    stop.executor = executor
    try:
        while not stop.requested and context.ok():
            try:
                executor.spin_once(timeout_sec=SPIN_SLICE_S)
            except ExternalShutdownException:
                break
            except Exception:
                if stop.requested or not context.ok():
                    break  # a callback failing because we are stopping: not an error
                raise
    finally:
        stop.executor = None
        with contextlib.suppress(Exception):
            executor.shutdown(timeout_sec=1.0)
        box = [executor]
        del executor
        executor_choice.drop_executor(box, stop.install)
    return 0


def settle_heap() -> None:
    """Collect start-up's garbage once, then move every surviving object to the permanent generation (``gc.freeze``).

    Why: a full (generation 2) collection walks every tracked object -- ~85,000 in a built fusion_node, 10-30 ms
    with every callback stalled (``gc_full_collection_ms`` of bench/bench_node_cost.py) -- and the collector starts
    one whenever enough objects have survived, at moments nobody chooses: a latency tail of the published pose. What
    exists once the node is built (modules, the node, its endpoints) lives as long as the process, so walking it again
    finds nothing; frozen, a later full collection walks only what the node made since. Frozen objects are still
    freed by reference counting (only cycles among them are left to the end of the process)."""
    gc.collect()
    gc.freeze()


def _release(name: str, held: dict) -> bool:
    """close() (stops device threads), destroy the node, shut rclpy down; False if close() raised."""
    ok = True
    node = held["node"]
    if node is not None:
        close = getattr(node, "close", None)
        if close is not None:
            try:
                close()
            except Exception:  # noqa: BLE001 - report, still release the node and rclpy
                print(f"[{name}] close() failed:\n{traceback.format_exc()}", file=sys.stderr, flush=True)
                ok = False
        with contextlib.suppress(Exception):
            late = wait_for_acks(node, SHUTDOWN_ACK_WAIT_S)
            if late:
                print(f"[{name}] samples on {', '.join(late)} still unacknowledged after {SHUTDOWN_ACK_WAIT_S:g} s "
                      "at shutdown (a reader gone or far behind)", file=sys.stderr, flush=True)
        with contextlib.suppress(Exception):
            node.destroy_node()
    if held["initialised"]:
        import rclpy

        with contextlib.suppress(Exception):
            rclpy.try_shutdown()
    return ok


def wait_for_acks(node, timeout_s: float, clock: Callable[[], float] | None = None) -> list[str]:
    """Wait until the samples of each of ``node``'s publishers are acknowledged by their matched readers, up to
    ``timeout_s`` for all of them together; returns the topics still unacknowledged (best-effort publishers never
    are: rclpy answers True at once). See :data:`SHUTDOWN_ACK_WAIT_S` for why."""
    from rclpy.duration import Duration

    now = clock or time.monotonic
    end = now() + timeout_s
    late = []
    for pub in list(node.publishers):
        left = max(end - now(), 0.0)
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9))):
            late.append(pub.topic_name)
    return late
