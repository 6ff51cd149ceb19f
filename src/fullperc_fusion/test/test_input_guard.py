"""InputGuard: who may publish on fusion_node's inputs, and the fail-closed verdict per topic (issue 40).

Pure: the publishers are what discovery would list, (fully qualified node name, GID hex); times are made up. A GID's
first 12 bytes are its process's (DDS GUID prefix), so the helpers below give each "process" its own prefix."""

from __future__ import annotations

from fullperc_fusion.input_guard import (
    ERROR,
    UNNAMED_GRACE_S,
    WARN,
    InputGuard,
    allowed,
    gid_hex,
    is_unknown,
    node_fqn,
    service_callers_line,
)

POSE = "/omc/tool/pose"
OTHER = "/ots/tool/pose"


def gid(process: int, entity: int = 1) -> str:
    """A GID of endpoint ``entity`` of process ``process`` (its 12-byte prefix), as the node formats it."""
    return gid_hex([process] * 12 + [0, 0, 0, entity])


HONEST = ("/omc_driver", gid(1))
INTRUDER = ("/intruder", gid(2))


def guard(allow=(), hold_s: float = 3.0) -> InputGuard:
    return InputGuard([POSE, OTHER], allow, hold_s)


def test_helpers_name_nodes_and_gids_as_the_messages_do():
    assert node_fqn("/", "omc_driver") == "/omc_driver" and node_fqn("/or1", "ndi") == "/or1/ndi"
    assert gid_hex([1, 15, 255]) == "010fff"
    assert is_unknown("/_NODE_NAME_UNKNOWN_") and is_unknown(node_fqn("_NODE_NAMESPACE_UNKNOWN_", "x"))
    assert not is_unknown("/omc_driver")


def test_a_topic_no_check_looked_at_is_open_and_unknown_topics_are_not_guarded():
    g = guard()
    assert g.is_open(POSE) and g.is_open("/not/an/input")


def test_the_first_node_seen_is_accepted_and_stays_the_accepted_one():
    g = guard()
    logs = g.update(POSE, [HONEST], 1.0)
    assert g.is_open(POSE) and g.topics[POSE].accepted == "/omc_driver"
    assert any(lvl == "info" and "/omc_driver" in line and HONEST[1] in line for lvl, line in logs)
    g.update(POSE, [], 2.0)                      # the driver leaves ...
    g.update(POSE, [INTRUDER], 3.0)              # ... and another node alone is not taken over
    assert not g.is_open(POSE)
    assert g.topics[OTHER].accepted is None, "per topic"


def test_two_nodes_at_the_first_look_are_none_taken_until_one_is_alone():
    g = guard()
    logs = g.update(POSE, [HONEST, INTRUDER], 1.0)
    assert not g.is_open(POSE) and g.topics[POSE].accepted is None
    assert any(lvl == "error" and "/intruder" in line and "/omc_driver" in line for lvl, line in logs)
    g.update(POSE, [HONEST], 2.0)
    assert g.topics[POSE].accepted == "/omc_driver" and g.draining() == [POSE]
    g.settle(2.0)
    assert g.is_open(POSE)


def test_allow_list_names_and_namespaces():
    assert allowed(["/omc_driver"], "/omc_driver") and not allowed(["/omc_driver"], "/omc_driver2")
    assert allowed(["/or1/"], "/or1/ndi_driver") and not allowed(["/or1/"], "/or10/ndi_driver")
    assert not allowed(["/or1/"], "/or1"), "a namespace entry names the nodes under it"
    g = guard(allow=["/omc_driver", "/or1/"])
    g.update(POSE, [HONEST, ("/or1/ndi_driver", gid(3))], 1.0)
    assert g.is_open(POSE), "every publisher allowed: open, even several"
    g.update(OTHER, [("/or10/ndi_driver", gid(4))], 1.0)
    assert not g.is_open(OTHER), "the allow-list replaces the first-seen rule: a node it does not name closes"
    assert "publishers.allow" in g.topics[OTHER].refused[0][2]


def test_a_name_discovery_does_not_know_yet_holds_the_topic_until_it_is_named():
    unknown = ("/_NODE_NAME_UNKNOWN_", gid(1))
    g = guard()
    g.update(POSE, [], 0.5)                      # the timer's look before anyone published
    g.update(POSE, [unknown], 1.0)
    assert not g.is_open(POSE) and g.holding(POSE) and g.topics[POSE].accepted is None
    level, _, values = g.status([POSE], 1.0)
    assert level == 0 and values["inputs_held"] == POSE and values["inputs_closed"] == "none", "not an error yet"
    g.update(POSE, [unknown], 1.1)
    assert g.holding(POSE) and not g.take_release(POSE)
    logs = g.update(POSE, [HONEST], 1.2)        # discovery named it: the first node seen, accepted
    assert g.is_open(POSE) and not g.holding(POSE) and g.draining() == [], "no queue to discard: nothing refused"
    assert g.take_release(POSE) and not g.take_release(POSE), "the held samples count, once"
    assert g.topics[POSE].accepted == "/omc_driver" and any("/omc_driver" in line for _, line in logs)
    assert g.status([POSE], 1.2)[2]["input_detect_ms"] is None, "a driver starting is no intrusion detected"


def test_a_held_topic_whose_publisher_is_named_and_refused_closes_and_its_samples_are_not_released():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    g.touch(POSE, 0.8)
    g.update(POSE, [HONEST, ("/_NODE_NAME_UNKNOWN_", gid(2))], 1.0)
    assert g.holding(POSE) and g.unresolved(POSE)
    logs = g.update(POSE, [HONEST, INTRUDER], 1.1)
    assert not g.holding(POSE) and not g.is_open(POSE) and not g.take_release(POSE)
    assert any(lvl == "error" and "/intruder" in line for lvl, line in logs)
    level, _, values = g.status([POSE], 1.1)
    assert level == ERROR and values["input_detect_ms"] == 200.0, "detected when the hold began: nothing used since"


def test_a_held_topic_whose_nameless_publisher_left_discards_its_queue_before_opening():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    g.update(POSE, [HONEST, ("/_NODE_NAME_UNKNOWN_", gid(2))], 1.0)
    g.update(POSE, [HONEST], 1.1)                # gone unnamed: its samples may be in the queue
    assert not g.take_release(POSE) and g.draining() == [POSE]
    g.settle(1.1)
    assert g.is_open(POSE)


def test_a_publisher_never_named_within_the_grace_closes_the_topic():
    g = guard(allow=["/"])                       # even an allow-list of everything takes no nameless publisher
    nameless = ("_NODE_NAMESPACE_UNKNOWN_/_NODE_NAME_UNKNOWN_", gid(1))
    g.update(POSE, [nameless], 1.0)
    g.update(POSE, [nameless], 1.0 + UNNAMED_GRACE_S)
    assert g.holding(POSE)
    logs = g.update(POSE, [nameless], 1.1 + UNNAMED_GRACE_S)
    assert not g.holding(POSE) and not g.is_open(POSE) and not g.take_release(POSE)
    assert any(lvl == "error" for lvl, _ in logs) and g.status([POSE], 2.5)[0] == ERROR


def test_a_second_publisher_closes_the_topic_and_its_leaving_reopens_it_after_the_queue_is_discarded():
    g = guard(hold_s=3.0)
    g.update(POSE, [HONEST], 0.0)
    g.touch(POSE, 0.9)
    logs = g.update(POSE, [HONEST, INTRUDER], 1.0)
    assert not g.is_open(POSE) and g.is_open(OTHER), "only that topic"
    err = [line for lvl, line in logs if lvl == "error"]
    assert err and POSE in err[0] and "/intruder" in err[0] and INTRUDER[1] in err[0]
    assert g.update(POSE, [HONEST, INTRUDER], 1.25) == [], "no change, nothing logged"
    level, msgs, values = g.status([POSE, OTHER], 1.5)
    assert level == ERROR and any(POSE in m and "/intruder" in m and INTRUDER[1] in m for m in msgs)
    assert values["inputs_closed"] == POSE and values["input_detect_ms"] == 100.0   # the check gap: 1.0 - 0.9
    g.update(POSE, [HONEST], 2.0)                # the intruder left: what was queued meanwhile goes first
    assert not g.is_open(POSE) and g.draining() == [POSE]
    assert g.status([POSE], 2.0)[0] == ERROR
    logs = g.settle(2.0)
    assert g.is_open(POSE) and g.draining() == [] and any(POSE in line for _, line in logs)
    assert g.status([POSE], 2.5)[0] == WARN, "held after reopening"
    assert g.status([POSE], 5.5)[0] == 0 and g.status([OTHER], 2.5)[0] == 0


def test_the_intruder_coming_back_while_the_queue_is_discarded_keeps_the_topic_closed():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    g.update(POSE, [HONEST, INTRUDER], 1.0)
    g.update(POSE, [HONEST], 2.0)
    g.update(POSE, [HONEST, INTRUDER], 2.1)
    assert g.draining() == [] and not g.is_open(POSE)
    g.settle(2.2)
    assert not g.is_open(POSE)


def test_a_restarted_driver_with_a_new_gid_and_the_same_name_is_accepted():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    g.update(POSE, [], 1.0)                      # stopped
    logs = g.update(POSE, [("/omc_driver", gid(5))], 2.0)   # a new process, a new GID
    assert g.is_open(POSE) and not [x for x in logs if x[0] == "error"]
    g.update(POSE, [("/omc_driver", gid(5)), ("/omc_driver", gid(5, 2))], 3.0)
    assert g.is_open(POSE), "two endpoints of one process: one driver"


def test_one_name_from_two_processes_at_once_closes_until_the_old_endpoint_is_gone():
    """A restarted driver whose old endpoint has not expired yet, or two drivers of one name (two OR PCs started the
    same launch): they cannot be told apart, so the topic is closed until one is gone."""
    g = guard(allow=["/omc_driver"])
    g.update(POSE, [HONEST], 0.0)
    logs = g.update(POSE, [HONEST, ("/omc_driver", gid(6))], 1.0)
    assert not g.is_open(POSE) and any(lvl == "error" and gid(6) in line for lvl, line in logs)
    g.update(POSE, [("/omc_driver", gid(6))], 2.0)
    g.settle(2.0)
    assert g.is_open(POSE)


def test_dropped_samples_are_counted_per_topic_and_in_the_status_of_the_targets_inputs():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    g.update(POSE, [HONEST, INTRUDER], 1.0)
    for _ in range(7):
        g.drop(POSE)
    g.drop(POSE, 3)                              # discarded at reopening
    assert g.dropped == {POSE: 10, OTHER: 0}
    _, msgs, values = g.status([POSE, OTHER], 1.5)
    assert values["input_dropped"] == 10 and values["input_dropped_by_topic"] == f"{POSE}: 10"
    assert "10 dropped" in msgs[0]
    assert g.status([OTHER], 1.5)[2]["input_dropped"] == 0, "a target that does not read the topic: not its count"


def test_the_service_line_says_who_could_have_called_and_that_rclpy_gives_no_caller():
    line = service_callers_line("/fusion_node/calibrate", ["/_ros2cli_123", "/planner"])
    assert "no caller identity" in line and "'/_ros2cli_123'" in line and "'/planner'" in line
    assert "none" in service_callers_line("/fusion_node/initialize", [])


def test_a_topic_closed_by_a_name_not_discovered_yet_asks_to_be_read_again():
    g = guard()
    g.update(POSE, [HONEST], 0.0)
    assert not g.unresolved(POSE)
    g.update(POSE, [HONEST, ("/_NODE_NAME_UNKNOWN_", gid(2))], 1.0)
    assert g.unresolved(POSE) and not g.unresolved(OTHER)
    g.update(POSE, [HONEST, INTRUDER], 1.1)
    assert not g.unresolved(POSE) and not g.is_open(POSE), "known now: closed, nothing more to learn"
