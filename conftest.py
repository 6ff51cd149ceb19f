"""Fixtures shared by every test in the repository (pytest loads this rootdir conftest first).

DDS isolation: every test that talks DDS gets its own ROS_DOMAIN_ID (an id no other test process on
this machine holds: fullperc_common.testing.claim_domain) and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST,
so nothing leaves this machine and parallel pytest runs do not cross-talk.

Session cache: results that many tests compute from the same committed sample bags (``bags/<profile>/<task>/``) --
the evaluation with fusion_node's default configuration (``cached_evaluate_bag``) and the raw-sensor rows of
``sensor_stats.bag_rows`` (``cached_bag_rows``) -- are computed once per test session and shared by the xdist workers
of that session (:class:`SessionCache`).

Run policy (hooks at the end): in CI a skipped test fails unless it is on ``ALLOWED_SKIPS``; the heaviest modules
start first (``test/durations.json``); figures tests report with ``record_property`` are printed in the summary.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import json
import os
import pickle
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fullperc_common.testing import Procs, claim_domain, installed_exe, wait_for  # noqa: F401 (re-exported)

ROOT = Path(__file__).resolve().parent

# A suite started in the background by a non-interactive shell (`make test &`, a CI runner's job) inherits SIGINT
# ignored, and so does every process a test starts: a child that does not install its own handler then ignores the
# SIGINT that Procs.stop sends, and each stop waited its 10 s grace for SIGKILL (one test took 20 s instead of 1 s).
# A Python-level handler is reset to SIG_DFL by exec, so the children get the default action back.
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def ros_env(monkeypatch) -> Iterator[dict[str, str]]:
    """Environment (also applied to this process) with a ROS_DOMAIN_ID no other test on this machine holds
    (fullperc_common.testing.claim_domain), released after the test's processes are gone."""
    with claim_domain() as lease:
        monkeypatch.setenv("ROS_DOMAIN_ID", str(lease.domain))
        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        monkeypatch.setenv("PYTHONUNBUFFERED", "1")
        yield dict(os.environ)


@pytest.fixture
def load_script():
    """Loader of ``scripts/<name>.py`` as a module (the scripts are run from a checkout, not installed): the tests
    of a script call its functions and its ``main`` in this process."""
    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    return load


@pytest.fixture
def procs(ros_env, tmp_path):
    """Process launcher for multi-process tests; kills leftovers even when the test fails."""
    ps = Procs(ros_env, tmp_path)
    yield ps
    ps.stop_all()


@pytest.fixture
def rclpy_context(ros_env):
    """An initialised rclpy context for in-test nodes, shut down afterwards."""
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    if ctx.ok():
        rclpy.shutdown(context=ctx)


@pytest.fixture
def python_exe() -> str:
    return sys.executable


# --------------------------------------------------------------------------------------------- session cache
class SessionCache:
    """Pickled results shared by the processes of one test session, each computed once.

    An entry is a file named by the SHA-256 of what determines it (the caller's ``key``: the input files' bytes and
    the configuration), so an entry can only be read for the same inputs. The first process that needs an entry
    computes it under an exclusive ``fcntl.flock`` of the entry's lock file; another one that needs it meanwhile waits
    on the lock and then reads the file. Pickle is lossless (floats, numpy arrays, dict order): what a test reads is
    bit for bit what computing it would give. The directory belongs to the session (:func:`session_cache`), so
    nothing is read across sessions.
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)

    def get(self, what: str, key: bytes, compute: Callable[[], Any]) -> Any:
        """The entry: read, or computed (and stored) by the first process that asks, the others waiting for it."""
        path, value = self._ensure(what, key, compute, wait=True)
        return value if path is None else pickle.loads(path.read_bytes())

    def prefetch(self, what: str, items: list[tuple[bytes, Callable[[], Any]]]) -> None:
        """Compute the missing entries of ``items`` (key, compute) that no other process is computing: processes that
        need the same entries at the same time share the work instead of waiting for each other."""
        for key, compute in items:
            self._ensure(what, key, compute, wait=False)

    def _ensure(self, what: str, key: bytes, compute: Callable[[], Any], wait: bool) -> tuple[Path | None, Any]:
        """(the entry's file, None) once it exists, (None, the value) when this call computed and stored it; (None,
        None) when ``wait`` is False and another process holds the entry's lock."""
        name = f"{what}-{hashlib.sha256(key).hexdigest()[:40]}"
        path = self.root / f"{name}.pkl"
        if path.exists():
            return path, None
        with open(self.root / f"{name}.lock", "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return None, None
            if path.exists():                      # computed while this process waited
                return path, None
            value = compute()
            tmp = self.root / f"{name}.{os.getpid()}.tmp"
            tmp.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
            os.replace(tmp, path)                  # atomic: a reader sees the whole entry or none
            return None, value                     # the lock is released when its file is closed


def files_digest(*paths: str | Path) -> bytes:
    """SHA-256 over the relative names and bytes of every file of each path (a file or a directory tree; symlinks
    followed, so a symlinked bag has the digest of its target)."""
    h = hashlib.sha256()
    for p in map(Path, paths):
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
        for f in files:
            h.update(f"\0{f.relative_to(p) if p.is_dir() else f.name}\0".encode())
            h.update(f.read_bytes())
    return h.digest()


def _config_key(target: str = "tool") -> bytes:
    """What the evaluator's configuration is made of: fusion_node's parameter values as used for ``target`` (the
    files they name, e.g. the params file itself, included by content) and the default layout."""
    from fullperc_eval.evaluation.config import replay_config
    from fullperc_fusion.margin.layout import default_layout_path

    _, flat = replay_config(None, target)
    named = [v for v in flat.values() if isinstance(v, str) and v and Path(v).is_file()]
    return json.dumps(flat, sort_keys=True, default=repr).encode() + files_digest(*named, default_layout_path())


@pytest.fixture(scope="session")
def session_cache(tmp_path_factory) -> SessionCache:
    """The :class:`SessionCache` of this test session. Under pytest-xdist each worker's basetemp is
    ``<session basetemp>/popen-gwN``: the cache lives in their common parent, which pytest creates afresh for every
    session; without xdist in the session's own basetemp."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return SessionCache(base.parent / f"session-cache-{os.environ.get('PYTEST_XDIST_TESTRUNUID', '')}")
    return SessionCache(base / "session-cache")


@pytest.fixture(scope="session")
def cached_evaluate_bag(session_cache):
    """``evaluate_bag(bag, target=target, progress=False)`` with fusion_node's default configuration, the
    :class:`~fullperc_eval.evaluation.metrics.Evaluation` (result and series), computed once per session for a bag's
    content, path and the configuration. A test that changes the configuration calls ``evaluate_bag`` itself."""
    from fullperc_eval.evaluation.metrics import evaluate_bag

    def get(bag: str | Path, target: str = "tool"):
        key = b"\0".join((b"evaluate_bag", str(bag).encode(), target.encode(), files_digest(bag),
                          _config_key(target)))
        return session_cache.get("evaluate", key, lambda: evaluate_bag(bag, target=target, progress=False))
    return get


class CachedBagRows:
    """``sensor_stats.bag_rows(bag, layout)`` (the raw-sensor rows of one bag: OMC rows, OTS rows), computed once per
    session for a bag's content, the layout and the configuration. Called like bag_rows, so a test can put it in
    bag_rows' place (``monkeypatch.setattr(sensor_stats, "bag_rows", cached_bag_rows)``) for the code that calls it
    (``profile_rows``, ``accuracy.calibrated_fusion_config``, ``scripts/orientation_phases.py --raw``)."""

    def __init__(self, cache: SessionCache) -> None:
        from fullperc_eval.evaluation.sensor_stats import bag_rows

        self.cache, self.bag_rows = cache, bag_rows

    def _item(self, bag: str | Path, layout) -> tuple[bytes, Callable[[], Any]]:
        key = b"\0".join((b"bag_rows", files_digest(bag), hashlib.sha256(pickle.dumps(layout)).digest(),
                          _config_key()))
        return key, lambda: self.bag_rows(bag, layout)

    def __call__(self, bag: str | Path, layout):
        return self.cache.get("bag_rows", *self._item(bag, layout))

    def prefetch(self, bags, layout) -> None:
        """Compute the rows of those ``bags`` no other process is computing (:meth:`SessionCache.prefetch`)."""
        self.cache.prefetch("bag_rows", [self._item(b, layout) for b in bags])


@pytest.fixture(scope="session")
def cached_bag_rows(session_cache) -> CachedBagRows:
    """:class:`CachedBagRows` of this session."""
    return CachedBagRows(session_cache)


# ---- CI: a skipped test fails the run unless it is on this list --------------------------------------------------
# A check that skips itself in CI never runs, and nobody notices. With CI=true (what .ci/run gets) a skip fails the
# test unless its node id and reason match an entry here; the list and the skips it allowed are printed at the end.
# Each entry: (node id regex, reason regex, why the environment may lack it).
ALLOWED_SKIPS: list[tuple[str, str, str]] = [
    # the C test doubles of the vendor SDKs are built with the machine's compiler (CI installs gcc; a user may not)
    (r"src/fullperc_drivers/test/test_(nokov_sdk|diana_api)\.py::", r"gcc not installed",
     "no C compiler on this machine"),
    # a system ROS 2 install brings tf2_msgs; then our stand-in package is not built and its checks do not apply
    (r"test/test_tf2_msgs_package\.py::", r"a system tf2_msgs is used", "a system ROS 2 provides tf2_msgs"),
    # the third-party NDI reader (scikit-surgerynditracker) is an optional test dependency
    (r"src/fullperc_eval/test/test_vega_emulator_sks\.py", r"sksurgerynditracker|ndicapy",
     "optional reader scikit-surgerynditracker not installed"),
]


def _ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def _skip_reason(report) -> str:
    lr = report.longrepr
    return str(lr[2]) if isinstance(lr, tuple) and len(lr) == 3 else str(lr)


def _allowed(nodeid: str, reason: str) -> str | None:
    import re

    return next((why for node, rx, why in ALLOWED_SKIPS if re.search(node, nodeid) and re.search(rx, reason)), None)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if not (_ci() and report.skipped) or hasattr(report, "wasxfail"):
        return
    reason = _skip_reason(report)
    if _allowed(report.nodeid, reason) is None:
        report.outcome = "failed"
        report.longrepr = (f"skipped in CI and not on conftest.ALLOWED_SKIPS: {reason}\n(a check that skips itself in "
                           "CI never runs: make it run, or add it to the list with the reason the environment lacks)")


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    """The same for a whole module skipped at collection (``pytest.importorskip``)."""
    outcome = yield
    report = outcome.get_result()
    if _ci() and report.skipped and _allowed(report.nodeid, _skip_reason(report)) is None:
        report.outcome = "failed"
        report.longrepr = f"skipped in CI and not on conftest.ALLOWED_SKIPS: {_skip_reason(report)}"


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Figures tests report with ``record_property`` (e.g. the demo's live-against-offline comparison), and in CI
    the allowed skips."""
    figures = [(r.nodeid, k, v) for key in ("passed", "failed") for r in terminalreporter.stats.get(key, [])
               if r.when == "call" for k, v in getattr(r, "user_properties", [])]
    if figures:
        terminalreporter.section("figures reported by tests")
        for nodeid, k, v in figures:
            terminalreporter.write_line(f"{k}: {v}  [{nodeid}]")
    if _ci():
        terminalreporter.section("CI: allowed skips (conftest.ALLOWED_SKIPS)")
        for node, rx, why in ALLOWED_SKIPS:
            terminalreporter.write_line(f"{node}  reason ~ {rx!r}: {why}")
        skipped = terminalreporter.stats.get("skipped", [])
        terminalreporter.write_line(f"skipped in this run: {len(skipped)}" + "".join(
            f"\n  {r.nodeid}: {_skip_reason(r)}" for r in skipped))


# ---- scheduling: the heaviest test modules start first ---------------------------------------------------------
# `make test` runs on several pytest-xdist workers with --dist loadscope (a module's tests on one worker). A module that
# takes a minute and starts last leaves one worker idle while the other finishes it: the suite's wall time is then
# the sum of the long tail. test/durations.json holds each module's measured seconds (setup + call + teardown,
# written by `make test PYTEST_ARGS=--write-durations`); modules it does not know count as DEFAULT_MODULE_S.
DURATIONS_FILE = ROOT / "test" / "durations.json"
DEFAULT_MODULE_S = 5.0


def pytest_addoption(parser):
    parser.addoption("--write-durations", action="store_true",
                     help="write every test module's summed duration to test/durations.json at the end of the run")


def _module(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


def pytest_collection_modifyitems(session, config, items):
    """Modules in descending order of their recorded duration (ties: collection order); tests keep their order
    inside a module. Every xdist worker sorts the same way, so their collections agree."""
    try:
        weights = json.loads(DURATIONS_FILE.read_text())
    except (OSError, ValueError):
        weights = {}
    first: dict[str, int] = {}
    for i, item in enumerate(items):
        first.setdefault(_module(item.nodeid), i)
    items.sort(key=lambda it: (-float(weights.get(_module(it.nodeid), DEFAULT_MODULE_S)), first[_module(it.nodeid)]))


_durations: dict[str, float] = {}


def pytest_runtest_logreport(report):
    _durations[_module(report.nodeid)] = _durations.get(_module(report.nodeid), 0.0) + report.duration


def pytest_sessionfinish(session, exitstatus):
    if session.config.getoption("--write-durations") and not hasattr(session.config, "workerinput") and _durations:
        DURATIONS_FILE.write_text(json.dumps({k: round(v, 1) for k, v in sorted(
            _durations.items(), key=lambda kv: -kv[1])}, indent=1) + "\n")
