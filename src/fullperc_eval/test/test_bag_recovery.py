"""A bag left behind by a killed recorder: every reader names the command that recovers it, and it does.

The bags here are written by a real process that is SIGKILLed after some flushes (no snapshot tricks): an MCAP
file without footer, a sqlite3 file whose commits are still in its write-ahead log (``<file>-wal``). rosbags
opens sqlite3 files read-only and immutable, so without the check the messages in the log are silently not
there (or the file looks like it has no tables). Every way a user opens a bag -- :class:`BagReader`,
``python -m fullperc_eval.bag info``, the installed ``play`` and ``evaluate`` -- must say that the bag is
incomplete and name ``python -m fullperc_eval.bag reindex BAG``; ``record --help`` documents it.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

from fullperc_common.testing import installed_exe
from fullperc_eval.bag import cli as bag_cli
from fullperc_eval.bag.errors import BagError
from fullperc_eval.bag.metadata import REINDEX_HINT
from fullperc_eval.bag.reader import BagReader

FLUSHED = 120  # messages written and flushed before the kill
UNFLUSHED = 15  # written after the last flush: lost by the kill

KILLED_WRITER = textwrap.dedent("""
    import os, signal, sys
    from fullperc_eval.bag.writer import BagWriter
    w = BagWriter(sys.argv[1], storage=sys.argv[2], flush_interval=3600).open()
    w.add_topic("/a", "std_msgs/msg/String")
    String = w.typestore.types["std_msgs/msg/String"]
    for i in range({flushed}):
        w.write_msg("/a", 1_700_000_000_000_000_000 + i * 1_000_000, String(data=f"m{{i}}"))
        if i % 40 == 39:
            w.flush()
    for i in range({flushed}, {flushed} + {unflushed}):
        w.write_msg("/a", 1_700_000_000_000_000_000 + i * 1_000_000, String(data=f"m{{i}}"))
    os.kill(os.getpid(), signal.SIGKILL)
""").format(flushed=FLUSHED, unflushed=UNFLUSHED)


@pytest.fixture(params=["mcap", "sqlite3"])
def killed_bag(request, tmp_path):
    bag = tmp_path / f"killed_{request.param}"
    p = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(bag), request.param], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == -signal.SIGKILL, p.stderr
    if request.param == "sqlite3":
        assert (bag / f"{bag.name}_0.db3-wal").stat().st_size > 0  # what a killed recorder leaves
    return bag


def _names_the_command(text: str, bag) -> None:
    assert "incomplete" in text and f"{REINDEX_HINT} {bag}" in text, text


def test_reader_names_the_recovery_command_and_reindex_recovers(killed_bag, capsys):
    with pytest.raises(BagError) as err:
        BagReader(killed_bag)
    _names_the_command(str(err.value), killed_bag)
    assert bag_cli.main(["info", str(killed_bag)]) == 1
    _names_the_command(capsys.readouterr().err, killed_bag)

    assert bag_cli.main(["reindex", str(killed_bag)]) == 0
    out = capsys.readouterr().out
    assert f"recovered {FLUSHED} messages" in out and f"{FLUSHED} messages, 1 topics" in out, out
    with BagReader(killed_bag) as r:
        got = [r.deserialize(m.data, m.msgtype).data for m in r.messages()]
    assert got == [f"m{i}" for i in range(FLUSHED)]  # every flushed message, in order, nothing else
    assert not list(killed_bag.glob("*-wal"))


def test_record_help_documents_recovery():
    p = subprocess.run([installed_exe("fullperc_eval", "record"), "--help"], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    assert f"{REINDEX_HINT} BAG" in p.stdout and "sqlite3" in p.stdout and "MCAP" in p.stdout, p.stdout


@pytest.mark.parametrize("exe", ["play", "evaluate"])
def test_installed_readers_name_the_recovery_command(killed_bag, exe, ros_env):
    p = subprocess.run([installed_exe("fullperc_eval", exe), str(killed_bag)], capture_output=True, text=True,
                       timeout=120, env=ros_env)
    assert p.returncode == 1, p.stdout + p.stderr
    assert "Traceback" not in p.stdout + p.stderr, p.stderr
    _names_the_command(" ".join(p.stderr.split()), killed_bag)
