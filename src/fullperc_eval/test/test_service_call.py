"""``call``: ``ros2 service call`` for systems without the ros2 CLI (the wheel path), against a tiny server here.

The server is an rclpy node of this process (std_srvs Trigger and SetBool), not fusion_node: what is tested is the
caller -- it waits for the service, fills the request from JSON/YAML, prints the response as one JSON line and
exits 0; without a server it exits 1 after ``--timeout``; a type that is no service or a field the request lacks
is status 2 before anything is started. Both ways in are run: the installed ``call`` and
``python -m fullperc_eval.bag call``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fullperc_common.testing import SpunNode, installed_exe
from fullperc_eval.bag.topic_tools import call_main


class Server(SpunNode):
    """``/h7_test/calibrate`` (Trigger) and ``/h7_test/enable`` (SetBool, answers with what it was sent)."""

    def __init__(self, context) -> None:
        from std_srvs.srv import SetBool, Trigger

        super().__init__(context, "call_test_server")
        self.calls = 0

        def trigger(_req, resp):
            self.calls += 1
            resp.success, resp.message = True, "calibrated: 3 links"
            return resp

        def set_bool(req, resp):
            resp.success, resp.message = bool(req.data), f"data={req.data}"
            return resp

        self.node.create_service(Trigger, "/h7_test/calibrate", trigger)
        self.node.create_service(SetBool, "/h7_test/enable", set_bool)
        self.start()


@pytest.fixture
def server(rclpy_context):
    s = Server(rclpy_context)
    yield s
    s.close()


def _run(args: list[str], env) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=300, env=env)


def test_installed_call_prints_the_trigger_response(server, ros_env):
    p = _run([installed_exe("fullperc_eval", "call"), "/h7_test/calibrate", "std_srvs/srv/Trigger",
              "--timeout", "120"], ros_env)
    assert p.returncode == 0, p.stdout + p.stderr
    assert [json.loads(ln) for ln in p.stdout.splitlines()] == [{"success": True, "message": "calibrated: 3 links"}]
    assert server.calls == 1


def test_module_call_fills_the_request(server, ros_env):
    p = _run([sys.executable, "-m", "fullperc_eval.bag", "call", "/h7_test/enable", "std_srvs/srv/SetBool",
              "{data: true}", "--timeout", "120"], ros_env)
    assert p.returncode == 0, p.stdout + p.stderr
    assert json.loads(p.stdout) == {"success": True, "message": "data=True"}


def test_no_server_exits_1_after_the_timeout(ros_env):
    p = _run([installed_exe("fullperc_eval", "call"), "/h7_test/nobody", "std_srvs/srv/Trigger", "--timeout", "0.5"],
             ros_env)
    assert p.returncode == 1 and "no server of /h7_test/nobody" in p.stderr, p.stdout + p.stderr
    assert "Traceback" not in p.stderr


@pytest.mark.parametrize("args, words", [
    (["/x", "std_msgs/msg/String"], ["not a service type"]),
    (["/x", "std_srvs/srv/NoSuch"], ["unknown message type", "NoSuch"]),
    (["/x", "std_srvs/srv/SetBool", "{value: true}"], ["no field 'value'"]),
    (["/x", "std_srvs/srv/SetBool", "[1, 2]"], ["must be a mapping"]),
])
def test_bad_type_or_request_is_status_2_before_rclpy(args, words, capsys):
    assert call_main(args) == 2           # in this process: returns before rclpy.init
    err = capsys.readouterr().err
    assert err.startswith("call: ") and all(w in err for w in words), err
