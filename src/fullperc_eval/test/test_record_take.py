"""How ``record`` takes messages from its subscriptions' queues (``--take``: ``Recorder.take_all`` / ``_drain``).

No DDS here: the subscriptions are stand-ins with the two members the recorder uses (``handle.take_message`` and
``msg_type``), so every mode's behaviour is pinned exactly; ``test_bag_record_play.py`` records through real rclpy
subscriptions in each mode and checks every message arrives, byte for byte.
"""

from __future__ import annotations

import argparse
from collections import deque

import pytest

from fullperc_eval.bag.record import TAKE_MODES, Recorder


class _Handle:
    """rclpy's subscription handle as the recorder uses it: a context manager with ``take_message``."""

    def __init__(self, topic: str, n: int) -> None:
        self.queue = deque((f"{topic}#{i}".encode(), {"received_timestamp": 10 * i, "source_timestamp": 10 * i - 1})
                           for i in range(n))
        self.takes = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None

    def take_message(self, msg_type, raw: bool):
        assert raw and msg_type == "raw-type"
        self.takes += 1
        return self.queue.popleft() if self.queue else None


class _Sub:
    def __init__(self, topic: str, n: int) -> None:
        self.handle, self.msg_type = _Handle(topic, n), "raw-type"


class _Writer:
    def __init__(self) -> None:
        self.rows: list[tuple[str, int, bytes, int]] = []

    def write(self, topic: str, t_recv: int, data: bytes, t_src: int) -> None:
        self.rows.append((topic, t_recv, data, t_src))


class _Log:
    def __init__(self) -> None:
        self.warnings: list[str] = []

    def warning(self, text: str) -> None:
        self.warnings.append(text)


class _Node:
    def __init__(self) -> None:
        self.log = _Log()

    def get_logger(self) -> _Log:
        return self.log


def _recorder(mode: str, queued: dict[str, int]) -> tuple[Recorder, _Writer]:
    args = argparse.Namespace(topics=[], topics_positional=[], exclude_topics=[], regex=None, exclude_regex=None,
                              qos_profile_overrides_path=None, take=mode)
    w = _Writer()
    rec = Recorder(_Node(), w, args)
    rec.subs = {t: _Sub(t, n) for t, n in queued.items()}
    return rec, w


QUEUED = {"/a": 3, "/b": 0, "/c": 5}


def _payloads(w: _Writer) -> list[bytes]:
    return [r[2] for r in w.rows]


def test_poll_takes_every_queue_in_each_topics_order_and_says_when_all_are_empty():
    rec, w = _recorder("poll", QUEUED)
    assert rec.polling and rec.take_all() is False   # every queue emptied: the loop may sleep
    assert _payloads(w) == [f"/a#{i}".encode() for i in range(3)] + [f"/c#{i}".encode() for i in range(5)]
    assert all(r[2].startswith(r[0].encode()) for r in w.rows)                  # each written under its own topic
    assert [(r[1], r[3]) for r in w.rows[:3]] == [(0, -1), (10, 9), (20, 19)]  # reception / source times kept
    assert rec.received == 8 and rec.callbacks == 0 and not rec.node.log.warnings
    assert rec.take_all() is False and len(w.rows) == 8


def test_poll_budget_is_per_topic_so_a_backlog_on_one_does_not_starve_the_others():
    rec, w = _recorder("poll", {"/a": 10, "/b": 2, "/c": 4})
    rec.DRAIN_MAX = 4   # instance attribute: the class's stays
    assert rec.take_all() is True   # /a and /c reached the budget: take again at once
    assert _payloads(w) == [b"/a#0", b"/a#1", b"/a#2", b"/a#3", b"/b#0", b"/b#1",
                            b"/c#0", b"/c#1", b"/c#2", b"/c#3"]
    assert rec.take_all() is True and _payloads(w)[10:] == [b"/a#4", b"/a#5", b"/a#6", b"/a#7"]
    assert rec.take_all() is False and _payloads(w)[14:] == [b"/a#8", b"/a#9"]
    assert Recorder.DRAIN_MAX == 500


def test_callback_takes_only_the_callbacks_own_queue():
    rec, w = _recorder("callback", QUEUED)
    assert not rec.polling
    rec._drain("/c")
    assert _payloads(w) == [f"/c#{i}".encode() for i in range(5)]
    assert rec.subs["/a"].handle.takes == 0 and len(rec.subs["/a"].handle.queue) == 3


@pytest.mark.parametrize("mode", ["executor", "poll"])
def test_a_callback_takes_nothing_more_unless_in_callback_mode(mode):
    rec, w = _recorder(mode, QUEUED)
    rec._drain("/a")
    assert w.rows == [] and all(s.handle.takes == 0 for s in rec.subs.values())


@pytest.mark.parametrize("mode", ["poll", "callback"])
def test_rclpy_internals_changed_falls_back_to_one_executor_round_per_message_with_a_warning(mode):
    rec, w = _recorder(mode, QUEUED)
    rec.subs["/a"].handle = object()   # no take_message / not a context manager, as if rclpy's internals had moved
    rec.take_all() if mode == "poll" else rec._drain("/a")
    assert rec._no_drain and not rec.polling   # _run spins the executor from now on
    assert len(rec.node.log.warnings) == 1 and "one executor round per message" in rec.node.log.warnings[0]
    rows = len(w.rows)
    rec._drain("/c")
    assert len(w.rows) == rows   # every message comes through its own callback


def test_modes_are_the_parsers_choices_and_poll_is_the_default():
    from fullperc_eval.bag.record import build_parser

    ap = build_parser()
    assert ap.parse_args(["--topics", "/x"]).take == "poll"
    assert {ap.parse_args(["--take", m, "--topics", "/x"]).take for m in TAKE_MODES} == set(TAKE_MODES)
    with pytest.raises(SystemExit):
        ap.parse_args(["--take", "some", "--topics", "/x"])
