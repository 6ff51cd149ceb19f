"""/tf and /tf_static in a bag written by our recorder decode with rosbags' own Jazzy type store (issue 17 item 1).

A publisher process (this file run as a script) sends the static tree on /tf_static (transient local) before the
recorder exists, then, once the recorder is matched, N ``base -> tool`` transforms on /tf. The bag is read with
``rosbags.rosbag2.Reader`` and decoded with ``get_typestore(Stores.ROS2_JAZZY)`` (rosbags' built-in definitions,
not the ones stored in the bag), and its metadata's type hash is rosbags'/upstream's.
"""

from __future__ import annotations

import signal
import sys
import time

import pytest

from fullperc_common.testing import Procs, installed_exe, wait_for

N = 50


def publish() -> int:
    import rclpy

    from fullperc_common.tf import Broadcaster, StaticBroadcaster, transform_stamped

    rclpy.init()
    node = rclpy.create_node("tf_bag_pub")
    static, dyn = StaticBroadcaster(node), Broadcaster(node)
    static.send([transform_stamped(1, "omc", "base", p=[1.0, 0.5, 0.8], q_xyzw=[0, 0, 0.258819, 0.9659258]),
                 transform_stamped(1, "base", "ots", p=[2.0, 0.0, 0.7], q_xyzw=[0, 0, 1.0, 0.0])])
    print("STATIC SENT", flush=True)
    end = time.monotonic() + 120
    while dyn.pub.get_subscription_count() == 0 and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    for k in range(N):
        dyn.send([transform_stamped(1_000_000_000 + k * 10_000_000, "base", "tool", p=[0.5, 0.01 * k, 0.3],
                                    q_xyzw=[0, 0, 0, 1])])
        rclpy.spin_once(node, timeout_sec=0.01)
    end = time.monotonic() + 2.0   # keep the writers alive while the recorder takes the last messages
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print("DONE", flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


@pytest.mark.system
def test_recorded_tf_decodes_with_rosbags_jazzy_typestore(procs, tmp_path, python_exe):
    import yaml
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    pub = procs.start([python_exe, __file__, "publish"], name="pub")
    wait_for(lambda: "STATIC SENT" in Procs.log(pub) or pub.poll() is not None, 60, what="static transforms sent")
    bag = tmp_path / "bag"
    rec = procs.start([installed_exe("fullperc_eval", "record"), "-o", str(bag), "--topics", "/tf", "/tf_static"],
                      name="record")
    wait_for(lambda: "DONE" in Procs.log(pub) or pub.poll() is not None, 120, what="publisher DONE")
    assert "DONE" in Procs.log(pub), Procs.log(pub)
    assert procs.stop(rec, signal.SIGINT, timeout=20) == 0, Procs.log(rec)

    ts = get_typestore(Stores.ROS2_JAZZY)
    want = ts.hash_rihs01("tf2_msgs/msg/TFMessage")
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    topics = {t["topic_metadata"]["name"]: t["topic_metadata"] for t in meta["topics_with_message_count"]}
    assert {n: (m["type"], m["type_description_hash"]) for n, m in topics.items()} == {
        "/tf": ("tf2_msgs/msg/TFMessage", want), "/tf_static": ("tf2_msgs/msg/TFMessage", want)}
    assert "transient_local" in str(topics["/tf_static"]["offered_qos_profiles"])
    got: dict[str, list] = {}
    with Reader(bag) as r:
        for conn, _t, raw in r.messages():
            got.setdefault(conn.topic, []).append(ts.deserialize_cdr(raw, "tf2_msgs/msg/TFMessage"))
    dyn = [t for m in got["/tf"] for t in m.transforms]
    assert len(dyn) == N
    assert all((t.header.frame_id, t.child_frame_id) == ("base", "tool") for t in dyn)
    assert [round(t.transform.translation.y, 6) for t in dyn] == [round(0.01 * k, 6) for k in range(N)]
    assert dyn[3].header.stamp.sec == 1 and dyn[3].header.stamp.nanosec == 30_000_000
    # the static tree, published before the recorder started (transient local), is in the bag
    assert len(got["/tf_static"]) == 1
    assert {(t.header.frame_id, t.child_frame_id) for t in got["/tf_static"][0].transforms} == {
        ("omc", "base"), ("base", "ots")}


if __name__ == "__main__" and sys.argv[1:] == ["publish"]:
    sys.exit(publish())
