"""The SROS2 policy of docs/security.md: the XML builder (pure), the generator run against the demo graph's real
nodes, and the measured reason the wheel path cannot enforce it.

The generator test starts every ROS node of ``config/demo_graph.yaml`` with the graph's parameters on a private DDS
domain (``scripts/sros2_policy.py``), and checks the policy it wrote against the graph: every topic the recorder
records has a publishing enclave, each node may subscribe to its inputs, and each driver topic has exactly one
publishing enclave (the point of per-node enclaves: nobody else may publish an OMC or OTS pose). Tolerant of a busy
machine: liveness bounds only, no timing asserts.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from fullperc_common.testing import claim_domain, workspace_root
from fullperc_eval.graph.sros2_policy import (
    NODE_SERVICES,
    ROS_INTERNAL_PUBLISH,
    NodeAccess,
    PolicyError,
    build_policy,
    check_policy,
    dds_topics,
    enclave_path,
    fully_qualified,
    parse_policy,
    policy_xml,
)

ROOT = workspace_root()
GRAPH = ROOT / "src" / "fullperc_eval" / "config" / "demo_graph.yaml"

FUSION = NodeAccess("fusion_node", publish=frozenset({"/fullperc/tool/pose", "/tf", "/diagnostics"}),
                    subscribe=frozenset({"/omc/tool/pose", "/ots/tool/pose"}),
                    reply=frozenset({"/fusion_node/calibrate", "/fusion_node/initialize"}))
OMC = NodeAccess("omc_driver", publish=frozenset({"/omc/tool/pose", "/omc/tool/quality", "/diagnostics"}))
CALLER = NodeAccess("caller", ns="/or1", request=frozenset({"/fusion_node/calibrate"}))


# ---------------------------------------------------------------------------------------------- the builder (pure)
def test_policy_is_well_formed_with_one_enclave_per_node() -> None:
    text = policy_xml([FUSION, OMC, CALLER])
    root = ET.fromstring(text)          # well-formed
    check_policy(root)                  # and shaped as sros2's policy.xsd wants
    assert root.tag == "policy" and root.get("version") == "0.2.0"
    paths = [e.get("path") for e in root.find("enclaves")]
    assert paths == ["/fullperc/fusion_node", "/fullperc/omc_driver", "/fullperc/or1/caller"]
    prof = root.find("enclaves/enclave[@path='/fullperc/or1/caller']/profiles/profile")
    assert (prof.get("ns"), prof.get("node")) == ("/or1", "caller")


def test_allow_lists_are_exactly_the_nodes_own_plus_what_every_node_has() -> None:
    got = parse_policy(policy_xml([FUSION, OMC]))
    fusion = got["/fullperc/fusion_node"]
    assert fusion.publish == FUSION.publish | set(ROS_INTERNAL_PUBLISH)
    assert fusion.subscribe == FUSION.subscribe        # nothing added that the node does not read
    assert fusion.reply == FUSION.reply | {f"/fusion_node/{s}" for s in NODE_SERVICES}
    assert fusion.request == frozenset()
    omc = got["/fullperc/omc_driver"]
    assert "/omc/tool/pose" in omc.publish and "/fullperc/tool/pose" not in omc.publish
    assert omc.subscribe == frozenset() and "/omc_driver/get_parameters" in omc.reply
    assert "/fusion_node/get_parameters" not in omc.reply      # parameter services are per node
    raw = parse_policy(policy_xml([FUSION], ros_internal=False))["/fullperc/fusion_node"]
    assert raw == FUSION


def test_empty_rule_lists_are_left_out() -> None:
    root = build_policy([NodeAccess("quiet")], ros_internal=False)
    with pytest.raises(PolicyError):     # a profile without a list is fine, but a policy of nothing is not useful
        check_policy(ET.fromstring("<policy version='0.2.0'><enclaves/></policy>"))
    prof = root.find("enclaves/enclave/profiles/profile")
    assert list(prof) == []
    subs = build_policy([FUSION]).findall("enclaves/enclave/profiles/profile/topics[@subscribe]")
    assert [[t.text for t in s] for s in subs] == [["/omc/tool/pose", "/ots/tool/pose"]]


def test_output_is_deterministic_whatever_the_input_order() -> None:
    nodes = [FUSION, OMC, CALLER]
    first = policy_xml(nodes)
    rng = random.Random(0)
    for _ in range(5):
        shuffled = [NodeAccess(n.node, n.ns, *(frozenset(rng.sample(sorted(s), len(s))) for s in
                                               (n.publish, n.subscribe, n.reply, n.request))) for n in nodes]
        rng.shuffle(shuffled)
        assert policy_xml(shuffled) == first
    names = [t.text for t in ET.fromstring(first).iter("topic")]
    fusion_pub = [t.text for t in ET.fromstring(first).find(
        "enclaves/enclave[@path='/fullperc/fusion_node']/profiles/profile/topics[@publish]")]
    assert fusion_pub == sorted(fusion_pub) and names


def test_two_nodes_of_one_name_are_refused() -> None:
    with pytest.raises(PolicyError, match="share the enclave"):
        build_policy([OMC, NodeAccess("omc_driver")])
    with pytest.raises(PolicyError, match="no nodes"):
        build_policy([])


@pytest.mark.parametrize("bad", [
    "<policy version='0.1.0'><enclaves><enclave path='/a'><profiles><profile ns='/' node='a'/></profiles></enclave>"
    "</enclaves></policy>",
    "<policy version='0.2.0'><enclaves><enclave path='/a'><profiles><profile ns='/' node='a'><topics publish='YES'>"
    "<topic>/x</topic></topics></profile></profiles></enclave></enclaves></policy>",
    "<policy version='0.2.0'><enclaves><enclave path='/a'><profiles><profile ns='/' node='a'><topics publish='ALLOW'>"
    "</topics></profile></profiles></enclave></enclaves></policy>",
    "<policy version='0.2.0'><enclaves><enclave path='/a'><profiles><profile ns='/' node='a'><topics reply='ALLOW'>"
    "<topic>/x</topic></topics></profile></profiles></enclave></enclaves></policy>",
    "<policy version='0.2.0'><enclaves><enclave path='/a'><profiles><profile ns='/' node='a'/></profiles></enclave>"
    "<enclave path='/a'><profiles><profile ns='/' node='a'/></profiles></enclave></enclaves></policy>",
])
def test_check_refuses_what_policy_xsd_refuses(bad: str) -> None:
    with pytest.raises(PolicyError):
        check_policy(ET.fromstring(bad))


def test_names_resolve_as_sros2s_permission_template_does() -> None:
    assert fully_qualified("/omc/tool/pose", "n", "/or1") == "/omc/tool/pose"
    assert fully_qualified("rosout", "n") == "/rosout"
    assert fully_qualified("omc/tool/pose", "n", "/or1") == "/or1/omc/tool/pose"
    assert fully_qualified("~/calibrate", "fusion_node", "/or1") == "/or1/fusion_node/calibrate"
    assert enclave_path("fusion_node") == "/fullperc/fusion_node"
    assert enclave_path("fusion_node", "/or1", "/site") == "/site/or1/fusion_node"


def test_dds_topics_follow_the_permission_template() -> None:
    d = dds_topics(NodeAccess("n", publish=frozenset({"/a"}), subscribe=frozenset({"/b"}),
                              reply=frozenset({"/n/srv"}), request=frozenset({"/m/cli"})))
    assert d["publish"] == {"rt/a", "rr/n/srvReply", "rq/m/cliRequest"}
    assert d["subscribe"] == {"rt/b", "rq/n/srvRequest", "rr/m/cliReply"}


# ------------------------------------------------------------------------------ the generator against the real nodes
def _recorded_topics() -> list[str]:
    record = next(p for p in yaml.safe_load(GRAPH.read_text())["processes"] if p["name"] == "record")
    rest = record["cmd"][record["cmd"].index("--topics") + 1:]
    return rest[:next((i for i, t in enumerate(rest) if t.startswith("-")), len(rest))]


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> dict[str, NodeAccess]:
    """policy.xml written by scripts/sros2_policy.py from the demo graph's nodes, read back."""
    tmp = tmp_path_factory.mktemp("sros2_policy")
    with claim_domain() as lease:
        env = {**os.environ, "ROS_DOMAIN_ID": str(lease.domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
               "PYTHONUNBUFFERED": "1"}
        out = tmp / "policy.xml"
        # start_new_session: a timeout kills the script's group; its nodes are in groups of their own, which the
        # script stops in its `finally` (SIGTERM is its KeyboardInterrupt)
        p = subprocess.Popen([sys.executable, str(ROOT / "scripts" / "sros2_policy.py"), "--out", str(out),
                              "--logs", str(tmp / "logs")], env=env, cwd=ROOT, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            log, _ = p.communicate(timeout=600)     # a liveness bound: six nodes starting on a busy 2-core machine
        except subprocess.TimeoutExpired:
            p.terminate()
            log, _ = p.communicate(timeout=120)
            pytest.fail(f"scripts/sros2_policy.py did not finish within 600 s:\n{log[-4000:]}")
    assert p.returncode == 0, log[-4000:]
    assert out.is_file(), log[-4000:]
    return parse_policy(out.read_text())


DEMO_NODES = {"fusion_node", "margin_node", "omc_driver", "ndi_driver", "diana_state", "rosbag2_recorder"}


@pytest.mark.system
def test_one_enclave_per_node_of_the_demo_graph(generated: dict[str, NodeAccess]) -> None:
    processes = [p for p in yaml.safe_load(GRAPH.read_text())["processes"] if p["name"] != "sim"]
    assert len(generated) == len(processes)
    assert set(generated) == {f"/fullperc/{n}" for n in DEMO_NODES}
    for path, acc in generated.items():
        assert path == enclave_path(acc.node, acc.ns)
        assert {"/rosout", "/parameter_events"} <= acc.publish
        assert f"/{acc.node}/get_parameters" in acc.reply


@pytest.mark.system
def test_every_recorded_topic_has_a_publishing_enclave(generated: dict[str, NodeAccess]) -> None:
    recorded = _recorded_topics()
    assert "/omc/tool/pose" in recorded and "/fullperc/instrument/final" in recorded
    published = set().union(*(a.publish for a in generated.values()))
    assert not sorted(set(recorded) - published), "recorded topics no node may publish"
    recorder = generated["/fullperc/rosbag2_recorder"]
    assert not sorted(set(recorded) - recorder.subscribe), "recorded topics the recorder may not read"
    assert not sorted(recorder.publish - set(ROS_INTERNAL_PUBLISH)), "the recorder publishes nothing of the graph's"


@pytest.mark.system
def test_each_node_may_read_its_inputs(generated: dict[str, NodeAccess]) -> None:
    fusion = generated["/fullperc/fusion_node"].subscribe   # the demo's fusion_node reads the frames (inputs: frames)
    assert {"/omc/bodies", "/ots/bodies", "/fullperc/tool/region", "/fullperc/instrument/region"} <= fusion, \
        sorted(fusion)
    assert not {t for t in fusion if t.endswith(("/pose", "/quality"))}, sorted(fusion)
    margin = generated["/fullperc/margin_node"].subscribe
    assert {"/fullperc/tool/pose", "/fullperc/instrument/pose", "/omc/base/pose"} <= margin, sorted(margin)
    assert {"/fusion_node/calibrate", "/fusion_node/initialize"} <= generated["/fullperc/fusion_node"].reply
    for driver in ("omc_driver", "ndi_driver", "diana_state"):   # a driver reads its device, not the graph
        assert generated[f"/fullperc/{driver}"].subscribe <= {"/parameter_events"}, driver


@pytest.mark.system
def test_a_pose_topic_has_one_publishing_enclave(generated: dict[str, NodeAccess]) -> None:
    """Why one enclave per node: under Enforce, nothing but the OMC driver's key may publish an OMC pose."""
    owners: dict[str, set[str]] = {}
    for path, acc in generated.items():
        for t in acc.publish:
            owners.setdefault(t, set()).add(path)
    shared = {"/rosout", "/parameter_events", "/diagnostics", "/tf"}   # by design: every node reports, two send TF
    for topic, paths in owners.items():
        if topic not in shared:
            assert len(paths) == 1, (topic, paths)
    assert owners["/omc/tool/pose"] == {"/fullperc/omc_driver"}
    assert owners["/ots/tool/pose"] == {"/fullperc/ndi_driver"}
    assert owners["/omc/bodies"] == {"/fullperc/omc_driver"} and owners["/ots/bodies"] == {"/fullperc/ndi_driver"}
    assert owners["/fullperc/tool/pose"] == {"/fullperc/fusion_node"}
    # every topic some node reads has a publishing enclave in the graph (no permission for a topic nobody sends)
    read = set().union(*(a.subscribe for a in generated.values())) - {"/parameter_events"}
    assert not sorted(read - set(owners)), "topics read that no node of the graph publishes"


# ----------------------------------------------------------------------- the wheel path: measured, not assumed
def _loaded_fast_dds(env: dict[str, str]) -> Path:
    """The libfastrtps this environment's rclpy actually maps (from /proc/self/maps after rclpy.init)."""
    code = ("import rclpy, re; rclpy.init(); n = rclpy.create_node('fast_dds_probe'); "
            "print(next(l.split()[-1] for l in open('/proc/self/maps') if re.search(r'libfastrtps\\.so', l))); "
            "n.destroy_node(); rclpy.shutdown()")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return Path(out.stdout.strip().splitlines()[-1])


@pytest.mark.system
def test_the_loaded_fast_dds_and_security(tmp_path: Path) -> None:
    """docs/security.md's measurement: the wheels' Fast DDS has no DDS Security plugins, and a node told to
    enforce security does not start (it never runs unprotected by mistake); a system install has the plugins."""
    with claim_domain() as lease:
        env = {**os.environ, "ROS_DOMAIN_ID": str(lease.domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
        lib = _loaded_fast_dds(env)
        data = lib.read_bytes()
        wheel = Path(sys.prefix).resolve() in lib.resolve().parents
        # a build without security (HAVE_SECURITY 0) keeps these warnings of its #else branches
        assert (b"DDS:Auth:PKI-DH" not in data and b"builtin.PKI-DH" not in data) == wheel, lib
        assert (b"Received PID_IDENTITY_TOKEN but security is disabled" in data) == wheel, lib
        enclave = tmp_path / "keystore" / "enclaves" / "fullperc" / "probe"
        enclave.mkdir(parents=True)
        sec = {**env, "ROS_SECURITY_ENABLE": "true", "ROS_SECURITY_STRATEGY": "Enforce",
               "ROS_SECURITY_KEYSTORE": str(tmp_path / "keystore")}
        # the participant (where security is set up) is made with the first node, not by rclpy.init
        code = ("import rclpy; rclpy.init(args=['x', '--ros-args', '--enclave', '/fullperc/probe']); "
                "rclpy.create_node('probe'); print('STARTED')")
        out = subprocess.run([sys.executable, "-c", code], env=sec, capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "STARTED" not in out.stdout, out.stdout + out.stderr
    expected = "doesn't have the security libraries" if wheel else "couldn't find all security files"
    assert expected in out.stderr, out.stderr[-2000:]
