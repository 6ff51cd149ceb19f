"""The multi-process test helpers' own behaviour (fullperc_common.testing)."""

import pytest

from fullperc_common.testing import wait_for


def test_wait_for_appends_the_detail_to_a_timeout_and_calls_it_only_then():
    calls = []

    def detail():
        calls.append(1)
        return "the peer had done nothing"

    assert wait_for(lambda: 7, 1.0, detail=detail) == 7
    assert calls == []
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the peer: the peer had done nothing$"):
        wait_for(lambda: False, 0.01, interval=0.001, what="the peer", detail=detail)
    assert calls == [1]
    with pytest.raises(pytest.fail.Exception, match=r"waiting for the peer$"):
        wait_for(lambda: False, 0.01, interval=0.001, what="the peer")


def test_wait_for_first_line_returns_once_the_process_wrote_or_exited(tmp_path):
    import os
    import sys

    from fullperc_common.testing import Procs, wait_for_first_line

    procs = Procs(dict(os.environ), tmp_path)
    try:
        talker = procs.start([sys.executable, "-c", "import time; print('up', flush=True); time.sleep(60)"],
                             name="talker")
        assert wait_for_first_line(procs, talker, 60).strip() == "up" and talker.poll() is None
        silent = procs.start([sys.executable, "-c", "pass"], name="silent")
        assert wait_for_first_line(procs, silent, 60) == "" and silent.returncode == 0
        mute = procs.start([sys.executable, "-c", "import time; time.sleep(60)"], name="mute")
        with pytest.raises(pytest.fail.Exception, match="waiting for python.*output"):
            wait_for_first_line(procs, mute, 0.2)
    finally:
        procs.stop_all()


def test_a_child_of_the_suite_stops_on_sigint_even_when_the_suite_was_started_in_the_background():
    """conftest.py undoes an inherited ignored SIGINT (a job started with ``&`` by a non-interactive shell): the
    processes tests start must react to the SIGINT Procs.stop sends, not sit out its 10 s grace."""
    import signal
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "import signal; print(signal.getsignal(signal.SIGINT).__name__)"],
                         capture_output=True, text=True, check=True).stdout.strip()
    assert signal.getsignal(signal.SIGINT) != signal.SIG_IGN
    assert out == "default_int_handler"


def test_udp_sockets_for_tests_stay_off_the_ports_dds_discovery_sends_to():
    """Each returned socket's port is below 7400 or at an offset >= 60 in its domain's 250-port block (RTPS default
    mapping); a quarter of the ephemeral ports are in such blocks, so 200 draws would meet one without the rule."""
    from fullperc_common.testing import udp_socket_off_dds_ports
    socks = [udp_socket_off_dds_ports() for _ in range(200)]
    try:
        for s in socks:
            port = s.getsockname()[1]
            assert port < 7400 or (port - 7400) % 250 >= 60, port
    finally:
        for s in socks:
            s.close()
