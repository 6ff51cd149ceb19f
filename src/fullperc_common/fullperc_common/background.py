"""One worker thread for a node's occasional heavy computations, so they do not stall its executor thread.

Why: a node's input callbacks and its timers share one executor thread. A computation of tens of milliseconds
there (fusion_node's stamp-offset estimate, ~20-35 ms every 10 s; a ``~/calibrate`` collection's robust means,
~70-100 ms once) holds every sample that arrives meanwhile for that long -- the tail of the fused latency. On
the worker the executor thread waits at most one GIL switch interval (``sys.getswitchinterval()``, 5 ms) at a
time, and numpy releases the GIL inside its loops.

:class:`Job` runs one call at a time: :meth:`Job.start` hands it the arguments (taken by the caller on its own
thread, so the worker reads nothing that thread still writes), :meth:`Job.poll` gives the result once it is
ready. ``background=False`` runs the call at once on the caller's thread (offline tools and tests, where the
result must not depend on thread timing). The worker is one thread per process, made on first use (the
interpreter's exit waits for a call still running: tens of milliseconds).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

_POOL: ThreadPoolExecutor | None = None
_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fullperc-background")
        return _POOL


class Job:
    """One computation of ``fn`` at a time, on the worker (``background``) or at once (module docstring)."""

    def __init__(self, fn: Callable[..., Any], background: bool) -> None:
        self.fn, self.background = fn, background
        self._future: Future | None = None

    @property
    def running(self) -> bool:
        """A call started and its result not yet taken by :meth:`poll`."""
        return self._future is not None

    @property
    def ready(self) -> bool:
        """The started call has finished; its result waits for :meth:`poll`."""
        return self._future is not None and self._future.done()

    def start(self, *args: Any) -> bool:
        """Start ``fn(*args)``; False (nothing started) while the previous call's result has not been taken."""
        if self._future is not None:
            return False
        if self.background:
            self._future = _pool().submit(self.fn, *args)
        else:
            self._future = f = Future()
            try:
                f.set_result(self.fn(*args))
            except Exception as e:   # given at poll, as from the worker
                f.set_exception(e)
        return True

    def poll(self) -> tuple[bool, Any]:
        """(True, the result) once the call has finished -- its exception raised here, on the caller's thread --,
        else (False, None). A result is given once."""
        if not self.ready:
            return False, None
        fut, self._future = self._future, None
        return True, fut.result()
