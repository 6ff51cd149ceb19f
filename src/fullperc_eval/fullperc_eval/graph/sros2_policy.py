"""SROS2 access-control policy XML from what each node of a graph publishes, subscribes to and serves.

Why: with DDS Security on (a system ROS 2 install, docs/security.md), a node may only use the topics and services
its signed ``permissions.xml`` grants; ``ros2 security create_permission KEYSTORE ENCLAVE policy.xml`` writes that
file from a policy in sros2's format (``sros2/policy/schemas/policy.xsd``, version 0.2.0)::

    <policy version="0.2.0"><enclaves><enclave path="/fullperc/fusion_node"><profiles>
      <profile ns="/" node="fusion_node">
        <topics publish="ALLOW"><topic>/fullperc/tool/pose</topic>...</topics>
        <topics subscribe="ALLOW"><topic>/omc/tool/pose</topic>...</topics>
        <services reply="ALLOW"><service>/fusion_node/calibrate</service>...</services>

One enclave per node, so a stolen or misconfigured key of one node grants only that node's topics (no second
publisher on ``/omc/tool/pose`` but the OMC driver's enclave). The lists come from the nodes themselves
(``scripts/sros2_policy.py`` reads them from the ROS graph of the running demo graph), never from a hand-kept list
that drifts from the code. This module is pure (no rclpy): building, checking and reading the XML.

Names are written fully qualified (``/omc/tool/pose``), which sros2's permissions template uses as they are: what
the file names is what the DDS permissions grant (``rt`` + name for topics; ``rq``/``rr`` + name + Request/Reply
for services: :func:`dds_topics`). Every node also gets what any rclpy node uses whether or not discovery showed it
yet -- ``/rosout``, ``/parameter_events`` and the parameter services -- as sros2's example policies grant them
(``test/policies/common/node/*.xml``); without them a node under ``Enforce`` fails at start-up.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field

from fullperc_fusion.input_guard import node_fqn  # the node name discovery reports, as fusion_node forms it

POLICY_VERSION = "0.2.0"
DEFAULT_PREFIX = "/fullperc"

# What every rclpy node of Jazzy has: /rosout (logging), /parameter_events (parameter changes) and the parameter
# services (sros2's common/node/{logging,parameters}.xml), plus ~/get_type_description (Jazzy's type-description
# service, on by default: parameter start_type_description_service).
ROS_INTERNAL_PUBLISH = ("/parameter_events", "/rosout")
NODE_SERVICES = ("describe_parameters", "get_parameter_types", "get_parameters", "get_type_description",
                 "list_parameters", "set_parameters", "set_parameters_atomically")

# (element, attribute, child) of a profile's rule lists, in the order they are written
_RULES = (("topics", "publish", "topic"), ("topics", "subscribe", "topic"),
          ("services", "reply", "service"), ("services", "request", "service"))


class PolicyError(ValueError):
    """A policy document that sros2 would refuse (it validates against policy.xsd); the message says where."""


def fully_qualified(name: str, node: str, ns: str = "/") -> str:
    """A policy expression resolved as sros2's permissions.xsl does: ``/x`` as is, ``~/x`` under the node, ``x``
    under the node's namespace."""
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        return node_fqn(ns, node) + name[1:]
    return ns.rstrip("/") + "/" + name


def enclave_path(node: str, ns: str = "/", prefix: str = DEFAULT_PREFIX) -> str:
    """The node's enclave: ``<prefix>/<node>`` (``<prefix>/<ns>/<node>`` in a namespace): one key per node, the
    name a deployment passes as ``--ros-args --enclave``."""
    return prefix.rstrip("/") + node_fqn(ns, node)


@dataclass(frozen=True)
class NodeAccess:
    """What one node uses, as fully qualified names: topics it publishes / subscribes to, services it serves
    (``reply``) and calls (``request``)."""

    node: str
    ns: str = "/"
    publish: frozenset[str] = field(default_factory=frozenset)
    subscribe: frozenset[str] = field(default_factory=frozenset)
    reply: frozenset[str] = field(default_factory=frozenset)
    request: frozenset[str] = field(default_factory=frozenset)

    @property
    def fqn(self) -> str:
        return node_fqn(self.ns, self.node)

    def with_ros_internal(self) -> NodeAccess:
        """This access plus what every rclpy node uses (``ROS_INTERNAL_PUBLISH``, ``NODE_SERVICES``)."""
        return NodeAccess(self.node, self.ns, self.publish | set(ROS_INTERNAL_PUBLISH), self.subscribe,
                          self.reply | {f"{self.fqn}/{s}" for s in NODE_SERVICES}, self.request)

    def rules(self) -> dict[str, frozenset[str]]:
        return {"publish": self.publish, "subscribe": self.subscribe, "reply": self.reply, "request": self.request}


def build_policy(nodes: Iterable[NodeAccess], prefix: str = DEFAULT_PREFIX, ros_internal: bool = True) -> ET.Element:
    """The ``<policy>`` element: one enclave per node, sorted by enclave path, each rule list sorted by name.

    Sorted so that the same graph always gives the same bytes (the file is committed or diffed against a previous
    run; a reordering must not look like a change). Empty rule lists are left out (policy.xsd wants at least one
    name in a list). ``ros_internal``: add what every rclpy node uses (:meth:`NodeAccess.with_ros_internal`).
    """
    by_path: dict[str, NodeAccess] = {}
    for n in nodes:
        path = enclave_path(n.node, n.ns, prefix)
        if path in by_path:
            raise PolicyError(f"two nodes named {n.fqn}: they would share the enclave {path}")
        by_path[path] = n.with_ros_internal() if ros_internal else n
    if not by_path:
        raise PolicyError("no nodes: a policy needs at least one enclave")
    policy = ET.Element("policy", version=POLICY_VERSION)
    enclaves = ET.SubElement(policy, "enclaves")
    for path in sorted(by_path):
        n = by_path[path]
        profiles = ET.SubElement(ET.SubElement(enclaves, "enclave", path=path), "profiles")
        profile = ET.SubElement(profiles, "profile", ns=n.ns, node=n.node)
        rules = n.rules()
        for element, attr, child in _RULES:
            names = sorted(rules[attr])
            if not names:
                continue
            lst = ET.SubElement(profile, element, {attr: "ALLOW"})
            for name in names:
                ET.SubElement(lst, child).text = name
    return policy


def policy_xml(nodes: Iterable[NodeAccess], prefix: str = DEFAULT_PREFIX, ros_internal: bool = True) -> str:
    """:func:`build_policy` as an indented XML document (with declaration), checked by :func:`check_policy`."""
    root = build_policy(nodes, prefix, ros_internal)
    check_policy(root)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def check_policy(root: ET.Element) -> None:
    """Raise :class:`PolicyError` where ``root`` breaks sros2's policy.xsd (0.2.0) or names something twice.

    Why here and not with the schema: validating against an XSD needs lxml, which the wheel path does not ship;
    these are the schema's rules for what this module writes (and reads back in :func:`parse_policy`)."""
    if root.tag != "policy" or root.get("version") != POLICY_VERSION:
        raise PolicyError(f"root must be <policy version=\"{POLICY_VERSION}\">, got <{root.tag} {root.attrib}>")
    if [c.tag for c in root] != ["enclaves"] or not len(root[0]):
        raise PolicyError("<policy> must hold exactly one <enclaves> with at least one <enclave>")
    seen: set[str] = set()
    for enc in root[0]:
        path = enc.get("path")
        if enc.tag != "enclave" or not path or not path.startswith("/"):
            raise PolicyError(f"<enclaves> may hold only <enclave path=\"/...\">, got <{enc.tag} {enc.attrib}>")
        if path in seen:
            raise PolicyError(f"enclave {path} appears twice")
        seen.add(path)
        if not len(enc) or any(c.tag != "profiles" for c in enc):
            raise PolicyError(f"enclave {path}: must hold <profiles>")
        for profiles in enc:
            if not len(profiles) or any(p.tag != "profile" for p in profiles):
                raise PolicyError(f"enclave {path}: <profiles> must hold <profile> elements")
            for prof in profiles:
                if prof.get("ns") is None or not prof.get("node"):
                    raise PolicyError(f"enclave {path}: <profile> needs ns and node")
                for lst in prof:
                    kinds = {"topics": ("topic", {"publish", "subscribe"}),
                             "services": ("service", {"reply", "request"})}
                    if lst.tag not in kinds and lst.tag != "actions":
                        raise PolicyError(f"enclave {path}: unexpected <{lst.tag}> in <profile>")
                    child, attrs = kinds.get(lst.tag, ("action", {"call", "execute"}))
                    if not lst.attrib or set(lst.attrib) - attrs or set(lst.attrib.values()) - {"ALLOW", "DENY"}:
                        raise PolicyError(f"enclave {path}: <{lst.tag} {lst.attrib}>: attributes must be "
                                          f"{sorted(attrs)} = ALLOW|DENY")
                    names = [c.text for c in lst]
                    if not names or any(c.tag != child or not c.text for c in lst):
                        raise PolicyError(f"enclave {path}: <{lst.tag}> must hold non-empty <{child}> elements")
                    if len(set(names)) != len(names):
                        raise PolicyError(f"enclave {path}: <{lst.tag} {lst.attrib}> names something twice")


def parse_policy(text: str) -> dict[str, NodeAccess]:
    """enclave path -> the ALLOW rules of its (first) profile, every name fully qualified: the inverse of
    :func:`policy_xml` (with the ROS-internal names it added), for checks of a generated file."""
    root = ET.fromstring(text)
    check_policy(root)
    out: dict[str, NodeAccess] = {}
    for enc in root[0]:
        prof = enc[0][0]
        node, ns = prof.get("node", ""), prof.get("ns", "/")
        rules: dict[str, set[str]] = {a: set() for _, a, _ in _RULES}
        for lst in prof:
            for attr, value in lst.attrib.items():
                if value == "ALLOW" and attr in rules:
                    rules[attr] |= {fully_qualified(c.text or "", node, ns) for c in lst}
        out[enc.get("path", "")] = NodeAccess(node, ns, **{k: frozenset(v) for k, v in rules.items()})
    return out


def dds_topics(access: NodeAccess) -> dict[str, set[str]]:
    """The DDS topic names a node's permissions.xml allows it to publish and subscribe to, as sros2's
    permissions.xsl maps the policy: topic ``/a`` -> ``rt/a``; a served service ``/s`` publishes ``rr/sReply`` and
    subscribes ``rq/sRequest``, a called one the other way round (ros_discovery_info, which sros2 adds for Fast DDS,
    is not part of the policy)."""
    pub = {f"rt{t}" for t in access.publish} | {f"rr{s}Reply" for s in access.reply} \
        | {f"rq{s}Request" for s in access.request}
    sub = {f"rt{t}" for t in access.subscribe} | {f"rq{s}Request" for s in access.reply} \
        | {f"rr{s}Reply" for s in access.request}
    return {"publish": pub, "subscribe": sub}
