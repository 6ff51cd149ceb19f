"""The driver nodes' shared pieces: console throttle, health report (level changes logged), topic tokens."""

from __future__ import annotations

import pytest

from fullperc_common.health import Health, HealthConfig
from fullperc_drivers.node_common import ConsoleThrottle, HealthReport, topic_name


class Log:
    def __init__(self):
        self.lines = []

    def info(self, t):
        self.lines.append(("info", t))

    def warning(self, t):
        self.lines.append(("warning", t))

    def error(self, t):
        self.lines.append(("error", t))


class Clock:
    t = 0.0

    def __call__(self):
        return self.t


def test_console_throttle_first_line_at_once_then_one_per_period_with_a_count():
    log, clk = Log(), Clock()
    c = ConsoleThrottle(lambda: log, period_s=5.0, clock=clk)
    assert c("link", "cannot connect: refused")
    for _ in range(9):
        clk.t += 0.5
        assert not c("link", "cannot connect: refused")
    assert c("other", "tool 'b' refused", level="info")  # keys are independent
    clk.t += 1.0
    assert c("link", "cannot connect: timeout")
    assert log.lines == [("warning", "cannot connect: refused"), ("info", "tool 'b' refused"),
                         ("warning", "cannot connect: timeout (9 more times in the last 6 s)")]


class FakeDiag:
    def __init__(self):
        self.sets = []

    def set_verdict(self, name, v, values=None):
        self.sets.append((name, v.level, v.message, values))


def test_health_report_publishes_every_verdict_and_logs_level_changes_only():
    log, clk = Log(), Clock()
    h = Health(["tool"], HealthConfig(stale_after_s=2.0), clock=clk)
    diag = FakeDiag()
    rep = HealthReport(diag, "link", h, ConsoleThrottle(lambda: log, clock=clk))
    rep.publish({"x": 1})  # start-up WARN: not news
    h.link_up()
    for k in range(10):
        clk.t += 0.1
        h.frame(k)
        h.good("tool")
    rep.publish()
    clk.t += 2.5
    rep.publish()
    rep.publish()
    assert [s[1] for s in diag.sets] == [1, 0, 2, 2] and diag.sets[0][3] == {"x": 1}
    assert log.lines == [("info", "link: OK again (receiving at 10.0 Hz)"),
                         ("warning", "link: ERROR: no new frames for 2.5 s (stream stopped)")]


@pytest.mark.parametrize("name, token", [("base", "base"), ("tool 2", "tool_2"), ("7rig", "b_7rig"), ("", "b_")])
def test_topic_name(name, token):
    assert topic_name(name) == token
