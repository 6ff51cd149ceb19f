"""The drivers' health ladder with an injected clock: never OK while nothing good is published."""

from __future__ import annotations

import pytest

from fullperc_common.health import ERROR, OK, WARN, Health, HealthConfig


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def run(self, h: Health, seconds: float, rate: float = 60.0, frame=None, tools=("tool", "base"),
            refuse=()) -> None:
        """Advance ``seconds`` delivering frames at ``rate``: each ``frame(k)`` number, good poses of ``tools``."""
        n = int(round(seconds * rate))
        for _ in range(n):
            self.t += 1.0 / rate
            num = frame() if frame else None
            if h.frame(num):
                for t in tools:
                    if t in refuse:
                        h.refused(t, "non-finite transform")
                    else:
                        h.good(t)


@pytest.fixture
def clk():
    return Clock()


def counter(start=1000):
    k = [start]

    def nxt():
        k[0] += 1
        return k[0]
    return nxt


def test_startup_warns_then_errors_without_frames(clk):
    h = Health(["tool"], clock=clk)
    h.link_down("cannot connect to 10.0.0.9:8765: [Errno 111] Connection refused")
    v = h.verdict()
    assert v.level == WARN and "no frame received yet" in v.message and "Connection refused" in v.message
    clk.t += 2.1
    v = h.verdict()
    assert v.level == ERROR and "no frame received yet after 2.1 s" in v.message
    assert "not connected: cannot connect" in v.message


def test_ok_while_poses_flow_and_rate(clk):
    h = Health(["tool", "base"], clock=clk, ok_text="tracking 2 tools")
    h.link_up()
    clk.run(h, 3.0, frame=counter())
    v = h.verdict()
    assert v.level == OK and v.message.startswith("tracking 2 tools at ") and v.message.endswith(" Hz")
    assert float(v.values["rate_hz"]) == pytest.approx(60.0, abs=1.01) and v.values["stalls"] == "0"


def test_frozen_frame_numbers_leave_ok_within_the_threshold_and_recover(clk):
    h = Health(["tool", "base"], HealthConfig(stale_after_s=2.0), clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 2.0, frame=nxt)
    frozen = nxt()
    h.frame(frozen)
    # the device keeps answering with the same frame number (and the same poses, which are never re-published)
    levels = []
    for _ in range(12):
        clk.t += 0.25
        for _ in range(15):
            h.frame(frozen)
        levels.append(h.verdict())
    first_bad = next(i for i, v in enumerate(levels) if v.level != OK)
    assert (first_bad + 1) * 0.25 <= 2.25  # left OK within stale_after_s (+ one evaluation period)
    v = levels[-1]
    assert v.level == ERROR and f"frame number frozen at {frozen}" in v.message and "no new frames for" in v.message
    assert int(v.values["repeated_frames"]) >= 12 * 15 and v.values["stalls"] == "1"
    clk.run(h, 0.1, frame=nxt)  # frames move on and poses flow again: OK at once
    assert h.verdict().level == OK


def test_driver_side_repeat_counts_explain_a_freeze(clk):
    h = Health(["tool"], clock=clk)
    h.link_up()
    clk.run(h, 1.0, frame=counter(), tools=("tool",))
    clk.t += 2.5
    h.repeated(400, number=1060)
    v = h.verdict()
    assert v.level == ERROR and "frame number frozen at 1060 (400 repeated)" in v.message


def test_every_frame_refused_is_an_error_naming_the_reason(clk):
    h = Health(["tool", "base"], clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 1.0, frame=nxt)
    clk.run(h, 1.0, frame=nxt, refuse=("tool", "base"))
    v = h.verdict()  # the last good poses are 1 s old: refusals warn, per tool
    assert v.level == WARN and "tool 'tool': 60 poses refused in the last 2 s (non-finite transform)" in v.message
    clk.run(h, 1.2, frame=nxt, refuse=("tool", "base"))
    v = h.verdict()
    assert v.level == ERROR and "every pose refused" in v.message and "non-finite transform" in v.message
    clk.run(h, 0.1, frame=nxt)
    v = h.verdict()  # good again, but refusals within the last 2 s still warn
    assert v.level == WARN and "refused in the last 2 s" in v.message
    clk.run(h, 2.1, frame=nxt)
    assert h.verdict().level == OK


def test_one_tool_refused_or_out_of_view_is_a_warning_per_tool(clk):
    h = Health(["tool", "base"], clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 2.5, frame=nxt, tools=("tool",))  # base never seen
    v = h.verdict()
    assert v.level == WARN and v.message == "tool 'base' not seen for 2.5 s"
    clk.run(h, 2.5, frame=nxt, tools=("tool", "base"), refuse=("base",))
    v = h.verdict()
    assert v.level == WARN and "tool 'base': every pose refused for 5.0 s (non-finite transform)" in v.message


def test_all_tools_out_of_view_warns_for_a_tracker_errors_for_an_arm(clk):
    tracker = Health(["tool", "base"], clock=clk)
    arm = Health(["arm"], item_kind="arm", output="joint state", frame="joint state", unseen_level=ERROR,
                 clock=clk)
    for h in (tracker, arm):
        h.link_up()
    nxt = counter()
    clk.run(tracker, 3.0, frame=nxt, tools=())
    arm.frame(1)
    v = tracker.verdict()
    assert v.level == WARN and v.message == "no tool seen for 3.0 s (tool, base)"
    assert arm.verdict().level == ERROR and "no arm seen" in arm.verdict().message


def test_repeated_reconnects_without_frames_then_recovery(clk):
    h = Health(["tool"], HealthConfig(reconnect_window_s=10.0, max_reconnects=3), clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 1.0, frame=nxt, tools=("tool",))
    # every BX body garbage: up, poll fails, down, up ... 130 times in 14 s, no frame
    for _ in range(130):
        clk.t += 14.0 / 130
        h.link_down("BX: reply does not parse")
        h.link_up()
        if clk.t > 103.0:
            v = h.verdict()
            assert v.level == ERROR, v.message
    assert "reconnects in the last 10 s, last error: BX: reply does not parse" in v.message
    clk.run(h, 0.5, frame=nxt, tools=("tool",))
    v = h.verdict()  # poses flow again; the burst of reconnects is still within the window
    assert v.level == WARN and "reconnects in the last 10 s" in v.message
    clk.run(h, 10.0, frame=nxt, tools=("tool",))
    assert h.verdict().level == OK


def test_a_tool_the_device_refused_warns_by_name_and_every_tool_refused_errors(clk):
    h = Health(["tool", "base"], clock=clk)
    h.link_up()
    h.item_failed("base", "refused by the device at PINIT (NDI ERROR0D) - ROM /x/base.rom")
    nxt = counter()
    clk.run(h, 3.0, frame=nxt, tools=("tool",))
    v = h.verdict()
    assert v.level == WARN
    assert v.message == "tool 'base': refused by the device at PINIT (NDI ERROR0D) - ROM /x/base.rom"
    assert v.values["last_good_s_ago"].endswith("base=refused")
    h.item_failed("tool", "refused")
    assert h.verdict().level == ERROR
    h.item_ok("tool")
    h.item_ok("base")
    clk.run(h, 0.1, frame=nxt, tools=("tool", "base"))
    assert h.verdict().level == OK


def test_problems_warn_only_while_recent(clk):
    h = Health(["tool"], clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 1.0, frame=nxt, tools=("tool",))
    h.problem("decode errors", 3, "bad OMC magic")
    v = h.verdict()
    assert v.level == WARN and v.message == "3 decode errors in the last 2 s (bad OMC magic)"
    clk.run(h, 2.1, frame=nxt, tools=("tool",))
    assert h.verdict().level == OK


def test_stream_stopped_is_an_error_and_counts_one_stall(clk):
    h = Health(["base"], HealthConfig(stale_after_s=3.0, frames_stale_after_s=1.0), item_kind="body", clock=clk)
    clk.run(h, 1.0, frame=counter(), tools=("base",))
    clk.t += 1.5
    v = h.verdict()
    assert v.level == ERROR and "no new frames for 1.5 s (stream stopped)" in v.message
    clk.t += 1.0
    assert h.verdict().values["stalls"] == "1"


def test_config_is_validated():
    with pytest.raises(ValueError):
        Health(config=HealthConfig(stale_after_s=0))


def test_a_short_link_cut_is_visible_and_clears_after_the_hold(clk):
    """A cut the driver repairs in 30 ms would never reach the stale rule: it is held as WARN for link_hold_s."""
    h = Health(["tool"], HealthConfig(stale_after_s=2.0, link_hold_s=1.0), clock=clk)
    h.link_up()
    nxt = counter()
    clk.run(h, 1.0, frame=nxt, tools=("tool",))
    assert h.verdict().level == OK
    h.link_down("connection reset by peer")
    v = h.verdict()
    assert v.level == WARN and "link down, reconnecting (connection reset by peer)" in v.message
    clk.t += 0.03
    h.link_up()
    clk.run(h, 0.5, frame=nxt, tools=("tool",))
    v = h.verdict()
    assert v.level == WARN and "link lost 0.5 s ago and re-established (connection reset by peer)" in v.message
    clk.run(h, 0.6, frame=nxt, tools=("tool",))
    assert h.verdict().level == OK


def test_the_first_connection_is_not_a_lost_link(clk):
    h = Health(["tool"], HealthConfig(link_hold_s=1.0), clock=clk)
    h.link_down("connecting")
    h.link_up()
    clk.run(h, 0.5, frame=counter(), tools=("tool",))
    assert h.verdict().level == OK
