"""Start-up and shut-down of the five installed nodes (issue 14 items 3, 4, 6), each in its own process.

* ``--help`` / ``-h`` prints a usage line and the node's parameter file and exits 0 without initialising
  rclpy: it runs with ``ROS_DOMAIN_ID=not-a-number``, under which the same executable without ``--help``
  fails in rclpy.init (checked as the control: exit 2, one line naming ROS_DOMAIN_ID).
* A float parameter given as ``0`` or ``abc``, a missing and a broken ``--params-file``: exit 2 and exactly one
  line on stderr that names the parameter or the file, no traceback.
* SIGINT (2 runs, the second sends a second SIGINT 20 ms after the first, during shutdown) and SIGTERM (1 run)
  while data flows through the node (its output topic is counted in this process; the signal goes only after
  new messages arrived): exit 0, no traceback. While the first run's data
  flows, the node's declared parameters are listed over its ``list_parameters`` service and each must appear
  in the parameter file that ``--help`` prints. soak/soak_signals.py repeats the SIGINT run 20 times per node.
* ROS naming and parameters (the drivers, margin_node and fusion_node, :data:`NS_NAMES`; docs/nodes.md "Namespaces and
  parameters"): started with ``-r __ns:=/or1`` and its shipped parameter file, every topic the node publishes or
  subscribes and every service it offers is under ``/or1`` (seen through the graph API of a node in this process),
  except the global ``/tf``, ``/tf_static``, ``/diagnostics`` and rclpy's ``/rosout`` and ``/parameter_events``.
  Over the node's parameter services: every parameter is read-only except those the node applies at run time
  (:data:`WRITABLE`); a set of a read-only one is refused with a reason naming it and changes nothing; a set of a
  writable one succeeds.

Which configuration case runs for which node (:data:`CASES_OF`): every node runs its help and a wrong type for its
float parameter in a process of its own (what only the node brings: its name, package and parameter file, its
parameter declarations, its ``main``); the other help flag, the other wrong type, the control and the two
``--params-file`` cases are decided by run_node's shared code before or without the node's own, the same way for
every node (src/fullperc_common/test/test_node_main.py runs each of them in-process), and run as a real process for
one node each -- not 35 processes (each ~0.7 s of CPU importing its node) on a 2-core machine.

Timeouts are liveness bounds only. Data sources: test/lifecycle_nodes.py (UDP for the OMC and Diana drivers,
synthetic poses for fusion and margin) and the installed vega_emulator for ndi_driver. The ten tests' runs start
together, side by side (each test's in a ROS domain of its own; a node's three signal runs one after another): most
of a run is a process starting, discovering its peers or shutting down, and these waits overlap.
"""

from __future__ import annotations

import re
import signal
import sys
from pathlib import Path

import pytest

from fullperc_common.testing import (
    Procs,
    RosSession,
    SideBySide,
    TopicCounter,
    installed_exe,
    poll_until,
    selected_cases,
    workspace_root,
)

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lifecycle_nodes import NODES, msg_type, signal_cycle, start_feed  # noqa: E402

pytestmark = pytest.mark.system
NAMES = list(NODES)
LIVENESS_S = 90.0
# (signal, seconds until the same signal again during shutdown or None); the second SIGINT run sends it twice. (A
# third, plain SIGINT run repeated the first; the repetitions are soak/soak_signals.py's.)
SIGNALS = [(signal.SIGINT, None), (signal.SIGINT, 0.02), (signal.SIGTERM, None)]
CASES = ("help", "h", "control", "int_for_float", "string_for_float", "missing_file", "broken_yaml")
# the configuration cases each node runs (module docstring): its help and a wrong type for its float parameter, and
# the cases run_node decides alone spread over the nodes, each on one of them
CASES_OF = {"omc_driver": ("help", "int_for_float", "control"),
            "ndi_driver": ("h", "string_for_float", "missing_file"),
            "diana_state": ("help", "int_for_float"),
            "fusion_node": ("h", "string_for_float", "broken_yaml"),
            "margin_node": ("help", "int_for_float")}
RCLPY_BUILTIN = {"use_sim_time", "start_type_description_service"}  # declared by rclpy in every node
# the nodes whose names and parameters follow the ROS conventions
NS_NAMES = ["omc_driver", "ndi_driver", "diana_state", "margin_node", "fusion_node"]
NS = "/or1"
GLOBAL_TOPICS = {"/tf", "/tf_static", "/diagnostics", "/rosout", "/parameter_events"}
# the parameters each node validates and applies at run time (all others are read-only); value for the set test
WRITABLE = {"omc_driver": {}, "ndi_driver": {}, "diana_state": {},
            "margin_node": {"layout_file": "", "threshold_deg": -1.0, "map_resolution": 0.2, "publish_map": True,
                            "hysteresis.margin_band_deg": 1.0, "hysteresis.min_dwell": 0.3},
            "fusion_node": {"alarm.hop_window": 3.0, "alarm.hop_max": 6, "alarm.bias_max": 0.03,
                            "alarm.reject_timeout": 2.0, "lag_warn": 0.3, "status_rate": 10.0}}
# a topic that shows the node is up and named (omc_driver makes its pose topics at the first frame of a body)
NS_READY = {"omc_driver": "/or1/omc/base/pose", "ndi_driver": "/or1/ots/tool/pose",
            "diana_state": "/or1/diana/joint_states", "margin_node": "/or1/fullperc/tool/region",
            "fusion_node": "/or1/fullperc/tool/pose"}


def reference_text(name: str) -> str:
    spec = NODES[name]
    return (workspace_root() / "install" / spec.pkg / "share" / spec.pkg / "config" / spec.params_file).read_text()


def _finish(procs: Procs, p) -> tuple[int | None, str, str]:
    if poll_until(lambda: p.poll() is not None, LIVENESS_S) is None:
        procs.stop(p, signal.SIGKILL)
        return None, procs.out(p), procs.err(p)
    return p.returncode, procs.out(p), procs.err(p)


def _help_and_bad_configuration(tmp: Path, name: str) -> list[str]:
    """Start the cases of ``name`` (:data:`CASES_OF`) at once; the problems found (none: as expected)."""
    spec = NODES[name]
    exe = installed_exe(spec.pkg, spec.name)
    fp = spec.float_param
    broken = tmp / "broken.yaml"
    broken.write_text(f"{name}:\n  ros__parameters:\n    {fp}: [1.0, 2.0\n")
    missing = str(tmp / "no_such_dir" / "params.yaml")
    with RosSession(tmp) as s:
        procs, ros_env = s.procs, s.env
        no_init = {**ros_env, "ROS_DOMAIN_ID": "not-a-number"}
        cases = {
            "help": ([exe, "--help"], no_init),
            "h": ([exe, "-h", "--ros-args", "-p", f"{fp}:=0"], no_init),
            "control": ([exe], no_init),
            "int_for_float": ([exe, "--ros-args", "-p", f"{fp}:=0"], ros_env),
            "string_for_float": ([exe, "--ros-args", "-p", f"{fp}:=abc"], ros_env),
            "missing_file": ([exe, "--ros-args", "--params-file", missing], ros_env),
            "broken_yaml": ([exe, "--ros-args", "--params-file", str(broken)], ros_env),
        }
        assert set(cases) == set(CASES)
        started = {case: procs.start_split(args, name=case, env=env) for case, (args, env) in cases.items()
                   if case in CASES_OF[name]}
        reference = reference_text(name)
        problems: list[str] = []

        def expect_fatal(case: str, rc, out: str, err: str, *words: str) -> None:
            lines = [ln for ln in err.splitlines() if ln.strip()]
            ok = (rc == 2 and len(lines) == 1 and lines[0].startswith(f"[{name}] fatal: ")
                  and all(w in lines[0] for w in words) and "Traceback" not in out + err)
            if not ok:
                problems.append(f"{case}: exit {rc}, expected 2 and one stderr line with {words}; "
                                f"stderr:\n{err[-2000:]}\nstdout:\n{out[-1000:]}")

        for case, p in started.items():
            rc, out, err = _finish(procs, p)
            if case in ("help", "h"):
                if not (rc == 0 and out.startswith(f"usage: ros2 run {spec.pkg} {name} ") and reference in out
                        and re.search(rf"^\s*{re.escape(fp)}:", out, re.M) and "Traceback" not in out + err):
                    problems.append(f"{case}: exit {rc}, expected 0 with usage and {spec.params_file}; "
                                    f"stdout:\n{out[-2000:]}\nstderr:\n{err[-2000:]}")
            elif case == "control":
                expect_fatal(case, rc, out, err, "ROS_DOMAIN_ID")
            elif case == "int_for_float":
                expect_fatal(case, rc, out, err, f"'{fp}'", "float", "0.0")
            elif case == "string_for_float":
                expect_fatal(case, rc, out, err, f"'{fp}'", "float", "abc")
            elif case == "missing_file":
                expect_fatal(case, rc, out, err, missing)
            else:
                expect_fatal(case, rc, out, err, str(broken))
        return problems


def _signals(tmp: Path, name: str) -> tuple[list, list[str]]:
    """The three signal runs of ``name``, one after another on one feed; (their results, the declared parameters).
    Each run counts the node's output with a counter of its own, made once the node is up (signal_cycle: a reader
    made before the node's participant appeared often waited for Fast DDS's next announcement, up to ~3 s)."""
    from rcl_interfaces.srv import ListParameters

    spec = NODES[name]
    installed_exe(spec.pkg, spec.name)
    with RosSession(tmp) as s:
        ros_args = start_feed(s.procs, spec, tmp)
        declared: list[str] = []

        def counter():
            return TopicCounter(s.context, {spec.output: msg_type(spec.output_type)})

        def list_parameters(_p, counter) -> None:
            resp = counter.call(ListParameters, f"/{name}/list_parameters", ListParameters.Request(), LIVENESS_S)
            declared.extend(resp.result.names if resp is not None else ["<list_parameters did not answer>"])

        results = [signal_cycle(s.procs, spec, ros_args, counter, sig, k, liveness_s=LIVENESS_S,
                                on_flowing=list_parameters if k == 0 else None, again_after_s=again)
                   for k, (sig, again) in enumerate(SIGNALS)]
        return results, declared


def _namespaced(tmp: Path, name: str) -> list[str]:
    """Start ``name`` in ``/or1`` with its shipped parameter file; the problems found (none: as expected)."""
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
    from rclpy.parameter import Parameter

    spec = NODES[name]
    exe = installed_exe(spec.pkg, spec.name)
    params = workspace_root() / "install" / spec.pkg / "share" / spec.pkg / "config" / spec.params_file
    with RosSession(tmp) as s:
        # UDP feeds (their ports as -p): omc_driver makes its topics per body seen; the others need no data here
        feed = start_feed(s.procs, spec, tmp)[1:] if spec.feed in ("omc", "diana") else []
        p = s.procs.start([exe, "--ros-args", "-r", f"__ns:={NS}", "--params-file", str(params), *feed],
                          name=f"{name}_ns")
        probe = TopicCounter(s.context, {}, node_name="fullperc_ns_probe")
        problems: list[str] = []
        try:
            def graph() -> tuple[set[str], set[str]]:
                g = probe.node
                return ({t for t, _ in g.get_publisher_names_and_types_by_node(name, NS)}
                        | {t for t, _ in g.get_subscriber_names_and_types_by_node(name, NS)},
                        {v for v, _ in g.get_service_names_and_types_by_node(name, NS)})

            def ready() -> bool:
                try:
                    return p.poll() is not None or NS_READY[name] in graph()[0]
                except Exception:   # the node is not in the graph yet
                    return False

            if poll_until(ready, LIVENESS_S) is None or p.poll() is not None:
                return [f"{NS_READY[name]} did not appear (exit {p.poll()}); log:\n{s.procs.log(p)[-3000:]}"]
            topics, services = graph()
            outside = sorted(t for t in topics if not t.startswith(NS + "/") and t not in GLOBAL_TOPICS)
            outside += sorted(v for v in services if not v.startswith(f"{NS}/{name}/"))
            if outside:
                problems.append(f"not under {NS}: {outside} (topics {sorted(topics)})")

            srv = f"{NS}/{name}"
            listed = probe.call(ListParameters, f"{srv}/list_parameters", ListParameters.Request(), LIVENESS_S)
            names = [n for n in (listed.result.names if listed else []) if n not in RCLPY_BUILTIN
                     and not n.startswith("qos_overrides.")]
            described = probe.call(DescribeParameters, f"{srv}/describe_parameters",
                                   DescribeParameters.Request(names=names), LIVENESS_S)
            if not names or described is None:
                return problems + [f"parameter services of {srv} did not answer"]
            ro = {d.name for d in described.descriptors if d.read_only}
            wrong = sorted((set(names) - ro) ^ set(WRITABLE[name]))
            if wrong:
                problems.append(f"read-only is wrong for {wrong} (writable: {sorted(set(names) - ro)})")

            sets = [Parameter("qos_depth", value=7)] + [Parameter(k, value=v) for k, v in WRITABLE[name].items()]
            answer = probe.call(SetParameters, f"{srv}/set_parameters",
                                SetParameters.Request(parameters=[x.to_parameter_msg() for x in sets]), LIVENESS_S)
            results = list(answer.results) if answer else []
            if len(results) != len(sets):
                return problems + [f"set_parameters of {srv} answered {results}"]
            r = results[0]
            if r.successful or "read-only" not in r.reason or "qos_depth" not in r.reason:
                problems.append(f"set of read-only qos_depth: successful={r.successful}, reason {r.reason!r}")
            problems += [f"set of writable {x.name}: {r.reason!r}" for x, r in zip(sets[1:], results[1:], strict=True)
                         if not r.successful]
            got = probe.call(GetParameters, f"{srv}/get_parameters", GetParameters.Request(names=["qos_depth"]),
                             LIVENESS_S)
            if got is None or got.values[0].type != ParameterType.PARAMETER_INTEGER or got.values[0].integer_value == 7:
                problems.append(f"qos_depth after the refused set: {got and got.values}")
        finally:
            probe.close()
            s.procs.stop(p)
        return problems


@pytest.fixture(scope="module")
def scenarios(request, tmp_path_factory):
    """Every selected test's runs started at once, side by side, each node's in a domain of its own: a test waits
    mostly for processes (starting, shutting down, discovering each other), and these waits overlap."""
    jobs = {}
    for name in NAMES:
        for test, fn in (("test_help_and_bad_configuration", _help_and_bad_configuration),
                         ("test_signals_with_data_flowing", _signals)):
            tmp = tmp_path_factory.mktemp(f"{test[5:9]}_{name}")   # here: mktemp is not thread-safe
            jobs[f"{test}[{name}]"] = (lambda fn=fn, tmp=tmp, name=name: fn(tmp, name))
    for name in NS_NAMES:
        tmp = tmp_path_factory.mktemp(f"ns_{name}")
        jobs[f"test_namespace_and_read_only_parameters[{name}]"] = (lambda tmp=tmp, name=name: _namespaced(tmp, name))
    sbs = SideBySide(jobs).start(selected_cases(request, jobs))
    yield sbs
    sbs.join()


def test_every_configuration_case_runs_for_a_node():
    """Each case in a real process for at least one node; each node its help and a wrong parameter type."""
    assert set(CASES_OF) == set(NAMES)
    assert set().union(*CASES_OF.values()) == set(CASES)
    for name, cases in CASES_OF.items():
        assert {"help", "h"} & set(cases) and {"int_for_float", "string_for_float"} & set(cases), name


@pytest.mark.parametrize("name", NAMES)
def test_help_and_bad_configuration(name, scenarios, request):
    problems = scenarios.result(request.node.name)
    assert not problems, "\n\n".join(problems)


@pytest.mark.parametrize("name", NAMES)
def test_signals_with_data_flowing(name, scenarios, request):
    results, declared = scenarios.result(request.node.name)
    bad = [f"run {k + 1} ({r.sig}, {r.flowed} messages flowed): {r.problem}\n{r.log[-3000:]}"
           for k, r in enumerate(results) if not r.clean]
    assert not bad, "\n\n".join(bad)

    reference = reference_text(name)
    unlisted = [n for n in declared if n not in RCLPY_BUILTIN and not n.startswith("qos_overrides.")
                and not re.search(rf"^[\s#]*{re.escape(n.rsplit('.', 1)[-1])}\s*:", reference, re.M)]
    assert declared and not unlisted, (f"parameters of {name} missing from config/{NODES[name].params_file} "
                                       f"(what --help prints): {unlisted}")


@pytest.mark.parametrize("name", NS_NAMES)
def test_namespace_and_read_only_parameters(name, scenarios, request):
    problems = scenarios.result(request.node.name)
    assert not problems, "\n\n".join(problems)


@pytest.mark.parametrize("name", NS_NAMES)
def test_shipped_parameter_file_applies_in_any_namespace(name):
    """The file's only key is ``/**/<node>``: a bare ``<node>`` matches ``/<node>`` only, so under
    ``-r __ns:=/or1`` its values would silently not apply."""
    import yaml

    doc = yaml.safe_load((workspace_root() / "src" / NODES[name].pkg / "config" / NODES[name].params_file).read_text())
    assert list(doc) == [f"/**/{name}"]
