"""First system test: a fullperc_msgs message crosses DDS between two separate processes.

Both ends are the installed executables (`install/fullperc_eval/lib/fullperc_eval/{pub,echo}`),
exactly what `ros2 run fullperc_eval pub|echo` would exec, on a test-unique domain over localhost.
"""

import json
import subprocess

from fullperc_common.testing import claim_domain, installed_exe


def test_tracking_quality_crosses_processes(procs, ros_env):
    echo = procs.start([installed_exe("fullperc_eval", "echo"), "/test/quality",
                        "--type", "fullperc_msgs/msg/TrackingQuality", "--count", "1", "--timeout", "60"],
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    pub = procs.start([installed_exe("fullperc_eval", "pub"), "/test/quality", "fullperc_msgs/msg/TrackingQuality",
                       json.dumps({"body": "tool", "visible": True, "fit_error": 0.00025, "frame_number": 4242,
                                   "markers_used": 4, "latency": 0.0035, "header": {"frame_id": "ots"}}),
                       "--rate", "10", "--wait-subscribers", "1"])
    out, err = echo.communicate(timeout=90)
    procs.stop(pub)
    assert echo.returncode == 0, err.decode()
    msg = json.loads(out.decode().splitlines()[0])
    assert msg["body"] == "tool" and msg["visible"] is True
    assert msg["frame_number"] == 4242 and msg["markers_used"] == 4
    assert abs(msg["fit_error"] - 0.00025) < 1e-9
    assert msg["header"]["frame_id"] == "ots"


def test_domain_isolation(procs, ros_env):
    """A publisher on another domain id must not be heard: the per-test domain really isolates."""
    with claim_domain() as other:
        env_other = dict(ros_env, ROS_DOMAIN_ID=str(other.domain))
        pub = procs.start([installed_exe("fullperc_eval", "pub"), "/test/iso", "std_msgs/msg/String",
                           '{"data": "leak"}', "--rate", "20"], env=env_other)
        echo = subprocess.run([installed_exe("fullperc_eval", "echo"), "/test/iso", "--type", "std_msgs/msg/String",
                               "--count", "1", "--timeout", "4"], env=ros_env, capture_output=True, timeout=60)
        procs.stop(pub)
    assert echo.returncode == 1 and echo.stdout == b""


def test_pub_rejects_unknown_field(ros_env):
    r = subprocess.run([installed_exe("fullperc_eval", "pub"), "/x", "fullperc_msgs/msg/Region", '{"nope": 1}',
                        "--count", "1"], env=ros_env, capture_output=True, timeout=60)
    assert r.returncode == 2 and b"no field 'nope'" in r.stderr
