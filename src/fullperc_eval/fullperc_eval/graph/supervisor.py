"""A small process supervisor: starts a graph of executables from YAML, waits for readiness,
prefixes their output, and shuts everything down cleanly.

`ros2 launch` is not available with the PyPI wheels, and the demo and system tests need the same
thing it does: separate processes, started in dependency order, each in its own process group so
that nothing outlives the supervisor. The graph format (see config/demo_graph.yaml)::

    name: demo
    env: {FOO: bar}                      # added to every process
    processes:
      - name: sim
        cmd: [fullperc_eval/sim, --task, "{task}"]   # "pkg/exe" -> install/pkg/lib/pkg/exe
        ready: {log: "serving"}          # regex on an output line (a list: every regex has matched a line)
                                         # | {port: 8765} | {delay: 0.5}
        after: [other]                   # start only once these are ready
        output: show | quiet | "filter:<regex>"      # what reaches the console (all goes to the log file)
        ends_graph: true                 # when it exits, the whole graph is shut down (task done)
        required: true                   # a non-zero exit of a required process fails the run
        grace: 30                        # its own shutdown grace [s] (default: the graph's ``grace``)
        when: "{with_diana}"             # optional: started only when this is true (YAML true/false, after filling)
    stop_stages: [[sim, omc], [fusion], [record]]   # optional; names every process once

`{name}` placeholders in cmd, env, ready and when are filled from ``--set name=value`` and the graph's ``vars``
(the defaults). A placeholder without either is a required argument: the graph does not load, and the one error
names every such argument at once (a bring-up with five device addresses to give should not fail five times). A
process whose ``when`` is false is left out, with its placeholders (its arguments are then not required); ``after``
and ``stop_stages`` may still name it.
Shutdown: SIGINT to each process group in reverse start order, SIGTERM after ``grace`` seconds (the
process's own, else the graph's), SIGKILL after another ``grace``. With ``stop_stages`` the stages stop in
order instead, the processes of one stage together (SIGINT to all, then each waited for): a node takes 1-2 s to
exit, and one at a time the demo's seven took ~10 s; the order that matters (the producers before the fusion node
drains its queues, the recorder last) is kept between stages.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from fullperc_common.executor_choice import signals_blocked


class GraphError(ValueError):
    """The graph description is invalid; the message names the file and the field."""


@dataclass
class ProcSpec:
    name: str
    cmd: list[str]
    ready: dict = field(default_factory=dict)
    after: list[str] = field(default_factory=list)
    output: str = "show"
    ends_graph: bool = False
    required: bool = True
    env: dict = field(default_factory=dict)
    grace: float | None = None   # this process's own shutdown grace [s] (None: the graph's)


@dataclass
class Graph:
    name: str
    processes: list[ProcSpec]
    env: dict = field(default_factory=dict)
    grace: float = 5.0
    ready_timeout: float = 60.0
    stop_stages: list[list[str]] | None = None   # None: one at a time, in reverse start order


def resolve_exe(token: str, root: Path) -> str:
    """'pkg/exe' -> the installed executable (what `ros2 run pkg exe` runs); else PATH / as given."""
    if "/" in token and not token.startswith(("/", ".")):
        pkg, exe = token.split("/", 1)
        for prefix in [root / "install" / pkg] + [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":")
                                                   if p]:
            cand = prefix / "lib" / pkg / exe
            if cand.exists():
                return str(cand)
        raise GraphError(f"executable {exe!r} of package {pkg!r} not found (is the workspace built?)")
    return shutil.which(token) or token


def load_graph(path: str | Path, values: dict[str, str]) -> Graph:
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise GraphError(f"{path}: cannot read graph: {e}") from e
    if not isinstance(doc, dict) or not isinstance(doc.get("processes"), list):
        raise GraphError(f"{path}: field 'processes' (a list) is missing")
    subst = {str(k): str(v) for k, v in (doc.get("vars") or {}).items()}
    subst.update(values)
    missing: dict[str, str] = {}   # placeholder -> where it was first needed

    def fill(s: str, where: str) -> str:
        def rep(m: re.Match) -> str:
            if m.group(1) not in subst:
                missing.setdefault(m.group(1), where)
                return ""
            return subst[m.group(1)]

        return re.sub(r"\{(\w+)\}", rep, str(s))

    procs = []
    names = set()
    skipped = set()
    for i, p in enumerate(doc["processes"]):
        where = f"processes[{i}]"
        if not isinstance(p, dict) or "name" not in p or "cmd" not in p:
            raise GraphError(f"{path}: {where}: 'name' and 'cmd' are required")
        if p["name"] in names | skipped:
            raise GraphError(f"{path}: {where}: duplicate name {p['name']!r}")
        if "when" in p and not _when(fill(p["when"], f"{where}.when"), f"{path}: {where}.when"):
            skipped.add(p["name"])
            continue
        names.add(p["name"])
        after = [a for a in (p.get("after") or []) if a not in skipped]
        for a in after:
            if a not in names:
                raise GraphError(f"{path}: {where}.after: {a!r} is not an earlier process")
        ready = {k: [fill(x, f"{where}.ready.{k}") for x in v] if isinstance(v, list) else fill(v, f"{where}.ready.{k}")
                 for k, v in (p.get("ready") or {}).items()}
        for rx in _log_patterns(ready):
            try:
                re.compile(rx)
            except re.error as e:
                raise GraphError(f"{path}: {where}.ready.log: bad regex {rx!r}: {e}") from e
        procs.append(ProcSpec(
            name=p["name"], cmd=[fill(c, f"{where}.cmd") for c in p["cmd"]], ready=ready,
            after=after, output=str(p.get("output", "show")), ends_graph=bool(p.get("ends_graph", False)),
            required=bool(p.get("required", True)),
            env={k: fill(v, f"{where}.env.{k}") for k, v in (p.get("env") or {}).items()},
            grace=_grace(p.get("grace"), f"{path}: {where}.grace")))
    env = {k: fill(v, f"env.{k}") for k, v in (doc.get("env") or {}).items()}
    if missing:
        raise GraphError(f"{path}: no value for " + ", ".join(f"{{{n}}} ({w})" for n, w in missing.items())
                         + "; give " + " ".join(f"--set {n}=..." for n in missing))
    stages = doc.get("stop_stages")
    if isinstance(stages, list):   # a left-out process stops with nothing; an emptied stage goes
        stages = [st for st in ([n for n in st if n not in skipped] if isinstance(st, list) else st
                                for st in stages) if st != []] if skipped else stages
    return Graph(name=str(doc.get("name", path.stem)), processes=procs, env=env,
                 grace=float(doc.get("grace", 5.0)), ready_timeout=float(doc.get("ready_timeout", 60.0)),
                 stop_stages=_stop_stages(stages, [q.name for q in procs], f"{path}: stop_stages"))


def _when(v: str, where: str) -> bool:
    """A process's ``when``, filled: YAML true/false (``true``, ``false``, ``yes``, ``no``, ``on``, ``off``)."""
    b = yaml.safe_load(v) if v.strip() else False
    if not isinstance(b, bool):
        raise GraphError(f"{where}: must be true or false, got {v!r}")
    return b


def _stop_stages(v, names: list[str], where: str) -> list[list[str]] | None:
    """``stop_stages``: None, or a list of lists of process names that names every process exactly once."""
    if v is None:
        return None
    if not isinstance(v, list) or not all(isinstance(st, list) and st for st in v):
        raise GraphError(f"{where}: must be a list of non-empty lists of process names, got {v!r}")
    seen: list[str] = [str(n) for st in v for n in st]
    if unknown := [n for n in seen if n not in names]:
        raise GraphError(f"{where}: {unknown[0]!r} is not a process of the graph")
    if dup := sorted({n for n in seen if seen.count(n) > 1}):
        raise GraphError(f"{where}: {dup[0]!r} is named more than once")
    if missing := [n for n in names if n not in seen]:
        raise GraphError(f"{where}: does not say when {', '.join(map(repr, missing))} stops")
    return [[str(n) for n in st] for st in v]


def _grace(v, where: str) -> float | None:
    if v is None:
        return None
    try:
        g = float(v)
    except (TypeError, ValueError):
        g = float("nan")
    if not g > 0 or g == float("inf"):
        raise GraphError(f"{where}: must be a number of seconds > 0, got {v!r}")
    return g


def _log_patterns(ready: dict) -> list[str]:
    """The ``ready.log`` regexes of a process (one string or a list), [] when readiness is not by log."""
    log = ready.get("log")
    return [] if log is None else [str(x) for x in log] if isinstance(log, list) else [str(log)]


class _Running:
    def __init__(self, spec: ProcSpec, popen: subprocess.Popen, log_path: Path) -> None:
        self.spec = spec
        self.popen = popen
        self.log_path = log_path
        self.ready = threading.Event()
        self.lines = 0


class Supervisor:
    def __init__(self, graph: Graph, log_dir: Path, root: Path, out=None) -> None:
        self.graph = graph
        self.log_dir = log_dir
        self.root = root
        self.out = out
        self.running: list[_Running] = []
        self._print_lock = threading.Lock()
        self._stop = threading.Event()
        self.failed: list[str] = []
        self.interrupted = 0  # the signal that asked for the stop (SIGINT, SIGTERM), 0 if none did
        self.completed = False  # a process marked ends_graph finished with exit 0: the graph's work is done
        self.reason = ""  # why the graph stopped, as said on the console

    def say(self, name: str, line: str) -> None:
        with self._print_lock:
            out = self.out or sys.stdout
            out.write(f"[{name}] {line}\n")
            out.flush()

    def _pump(self, r: _Running) -> None:
        spec = r.spec
        pending = [re.compile(rx) for rx in _log_patterns(spec.ready)]
        show_re = re.compile(spec.output[len("filter:"):]) if spec.output.startswith("filter:") else None
        with open(r.log_path, "w") as log:
            for raw in iter(r.popen.stdout.readline, b""):
                line = raw.decode(errors="replace").rstrip("\n")
                log.write(line + "\n")
                log.flush()
                r.lines += 1
                if pending:
                    pending = [rx for rx in pending if not rx.search(line)]
                    if not pending:
                        r.ready.set()
                if spec.output == "show" or (show_re is not None and show_re.search(line)):
                    self.say(spec.name, line)

    def _wait_ready(self, r: _Running) -> bool:
        spec = r.spec
        if "log" not in spec.ready and "port" not in spec.ready:
            # no condition (or a delay): ready once started -- whether it already exited is wait()'s business (a short
            # ends_graph process may be gone before this line runs on a busy machine: CI saw start() fail so)
            time.sleep(float(spec.ready.get("delay", 0.0)))
            r.ready.set()
            return True
        end = time.monotonic() + self.graph.ready_timeout
        while time.monotonic() < end and not self._stop.is_set():
            if r.popen.poll() is not None and not r.ready.is_set():
                return False
            if "log" in spec.ready:
                if r.ready.wait(0.05):
                    return True
            elif "port" in spec.ready:
                with socket.socket() as s:
                    s.settimeout(0.2)
                    if s.connect_ex(("127.0.0.1", int(spec.ready["port"]))) == 0:
                        r.ready.set()
                        return True
                time.sleep(0.05)
        return False

    def start(self) -> bool:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, PYTHONUNBUFFERED="1", **self.graph.env)
        for spec in self.graph.processes:
            if self._stop.is_set():
                return False
            cmd = [resolve_exe(spec.cmd[0], self.root)] + spec.cmd[1:]
            popen = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     env=dict(env, **spec.env), start_new_session=True)
            r = _Running(spec, popen, self.log_dir / f"{spec.name}.log")
            self.running.append(r)
            threading.Thread(target=self._pump, args=(r,), daemon=True).start()
            self.say("supervisor", f"started {spec.name} (pid {popen.pid}): {' '.join(spec.cmd)}")
            if not self._wait_ready(r):
                if self._stop.is_set():
                    return False
                self._stop_because(f"{spec.name} did not become ready (exit {popen.poll()}); see {r.log_path}")
                self.failed.append(spec.name)
                return False
        return True

    def _stop_because(self, reason: str) -> None:
        self.reason = reason
        self.say("supervisor", f"{reason}; shutting down")

    def wait(self, timeout: float | None = None) -> None:
        """Block until a process marked ends_graph exits, a required process dies, or a signal arrives."""
        end = None if timeout is None else time.monotonic() + timeout
        while not self._stop.is_set():
            for r in self.running:
                rc = r.popen.poll()
                if rc is None:
                    continue
                if r.spec.ends_graph:
                    if rc != 0:
                        self.failed.append(r.spec.name)
                    self.completed = rc == 0
                    self._stop_because(f"{r.spec.name} finished (exit {rc})")
                    return
                if r.spec.required and r.spec.name not in self.failed:
                    self.failed.append(r.spec.name)
                    self._stop_because(f"{r.spec.name} exited unexpectedly (exit {rc})")
                    return
            if end is not None and time.monotonic() > end:
                self._stop_because("time limit reached")
                return
            self._stop.wait(0.1)

    def request_stop(self, signum: int = 0, _frame=None) -> None:
        """Signal handler (SIGINT/SIGTERM): stop starting, stop waiting; :meth:`shutdown` does the rest.

        It only sets flags: printing here could deadlock on the print lock the interrupted code holds."""
        if signum and not self.interrupted:
            self.interrupted = signum
        self._stop.set()

    def shutdown(self) -> dict[str, int | None]:
        if self.interrupted and not self.reason:
            self._stop_because(f"interrupted ({signal.Signals(self.interrupted).name})")
        codes: dict[str, int | None] = {}
        running = {r.spec.name: r for r in self.running}
        stages = self.graph.stop_stages or [[r.spec.name] for r in reversed(self.running)]
        for stage in stages:
            rs = [running[n] for n in stage if n in running]
            threads = [threading.Thread(target=lambda r=r: codes.__setitem__(
                r.spec.name, stop_group(r.popen, r.spec.grace or self.graph.grace))) for r in rs]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
        return {r.spec.name: codes.get(r.spec.name) for r in reversed(self.running)}


def stop_group(p: subprocess.Popen, grace: float) -> int | None:
    """SIGINT the process group, then SIGTERM, then SIGKILL; returns the exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        if p.poll() is not None:
            break
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            break
        try:
            p.wait(grace if sig != signal.SIGKILL else None)
        except subprocess.TimeoutExpired:
            continue
    # the group may still hold children that ignored their parent's exit
    try:
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        return p.poll()
    # SIGKILL takes effect when the kernel next schedules each member: on a busy machine that is not at once. Wait
    # (bounded: an orphan's zombie stays a group member until init reaps it) until the group is gone, so that a
    # caller that got the exit codes back finds nothing of the graph still running.
    end = time.monotonic() + GROUP_GONE_WAIT_S
    while time.monotonic() < end and _group_has_live_members(p.pid):
        time.sleep(0.01)
    return p.poll()


GROUP_GONE_WAIT_S = 5.0


def _group_has_live_members(pgid: int) -> bool:
    """True while a process of group ``pgid`` is alive (not a zombie); from /proc, else ``killpg(pgid, 0)``."""
    try:
        entries = [d for d in os.listdir("/proc") if d.isdigit()]
    except OSError:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        return True
    for d in entries:
        try:
            fields = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":   # fields after "(comm)": state, ppid, pgrp, ...
            return True
    return False


@dataclass
class GraphOutcome:
    """How a graph run ended: what :func:`run_graph` returns as an exit code, and why."""

    rc: int  # 1 if a process failed (did not become ready, died, or an ends_graph process exited non-zero)
    codes: dict[str, int | None]  # exit code of every started process
    completed: bool  # a process marked ends_graph finished with exit 0 (e.g. the simulated task ran to its end)
    interrupted: int  # the signal (SIGINT/SIGTERM) that stopped the run, 0 if none
    reason: str  # why the graph stopped ("sim finished (exit 0)", "interrupted (SIGINT)", ...)


def execute_graph(path: str | Path, values: dict[str, str], log_dir: Path, root: Path,
                  timeout: float | None = None) -> GraphOutcome:
    """Run a graph until it ends (see :meth:`Supervisor.wait`), shut it down, and say how it ended."""
    graph = load_graph(path, values)
    sup = Supervisor(graph, log_dir, root)
    old = {s: signal.signal(s, sup.request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        if sup.start():
            sup.wait(timeout)
    finally:
        codes = sup.shutdown()
        with signals_blocked():   # a signal in the swap waits for the old handler (node_main: the same race)
            for s, h in old.items():
                signal.signal(s, h)
    sup.say("supervisor", "all processes stopped: " + ", ".join(f"{k}={v}" for k, v in codes.items()))
    return GraphOutcome(1 if sup.failed else 0, codes, sup.completed and not sup.failed, sup.interrupted,
                        sup.reason)


def run_graph(path: str | Path, values: dict[str, str], log_dir: Path, root: Path,
              timeout: float | None = None) -> int:
    """:func:`execute_graph`'s exit code: 1 if a process failed, else 0."""
    return execute_graph(path, values, log_dir, root, timeout).rc
