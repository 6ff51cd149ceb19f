"""src/tf2_msgs (issue 17 item 1): on the wheel path `make build` builds it and its TFMessage is upstream's (same
RIHS01 type hash as rosbags' Jazzy store); with a system tf2_msgs on AMENT_PREFIX_PATH `make build` skips it
(scripts/colcon_skip.sh)."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP = ROOT / "scripts" / "colcon_skip.sh"


def _system_tf2_msgs(env_path: str) -> bool:
    return any((Path(p) / "share/ament_index/resource_index/packages/tf2_msgs").is_file()
               for p in env_path.split(":") if p and not p.startswith(str(ROOT / "install")))


def _skip_args(ament_prefix_path: str) -> str:
    env = dict(os.environ, AMENT_PREFIX_PATH=ament_prefix_path)
    return subprocess.run([str(SKIP)], env=env, capture_output=True, text=True, check=True).stdout.strip()


def test_colcon_skip_only_with_a_tf2_msgs_outside_the_workspace(tmp_path):
    system = tmp_path / "opt_ros_jazzy"
    (system / "share/ament_index/resource_index/packages").mkdir(parents=True)
    (system / "share/ament_index/resource_index/packages/tf2_msgs").write_text("")
    ours = ROOT / "install" / "tf2_msgs"
    venv = tmp_path / "venv"
    assert _skip_args(f"{ours}:{venv}") == ""
    assert _skip_args("") == ""
    assert _skip_args(f"{ours}:{venv}:{system}") == "--packages-skip tf2_msgs"
    assert _skip_args(f"{system}") == "--packages-skip tf2_msgs"


def test_makefile_build_passes_the_skip_arguments_to_colcon():
    mk = (ROOT / "Makefile").read_text()
    build = mk[mk.index("\nbuild:"):].split("\n\n")[0]
    assert "colcon build" in build and "$$(scripts/colcon_skip.sh)" in build
    assert build.index("colcon_skip.sh") < build.index("--cmake-args")   # --cmake-args swallows what follows


def test_workspace_definition_is_upstreams():
    from rosbags.typesys import Stores, get_typestore

    assert (ROOT / "src/tf2_msgs/msg/TFMessage.msg").read_text().strip() == \
        "geometry_msgs/TransformStamped[] transforms"
    ts = get_typestore(Stores.ROS2_JAZZY)
    _, fields = ts.fielddefs["tf2_msgs/msg/TFMessage"]
    assert [f[0] for f in fields] == ["transforms"]


@pytest.mark.skipif(_system_tf2_msgs(os.environ.get("AMENT_PREFIX_PATH", "")),
                    reason="a system tf2_msgs is used (make build skips src/tf2_msgs)")
def test_wheel_path_builds_tf2_msgs_with_upstreams_type_hash():
    from rosbags.typesys import Stores, get_typestore

    import tf2_msgs.msg

    assert Path(tf2_msgs.msg.__file__).is_relative_to(ROOT / "install" / "tf2_msgs")   # symlink install
    desc = json.loads((ROOT / "install/tf2_msgs/share/tf2_msgs/msg/TFMessage.json").read_text())
    own = next(h["hash_string"] for h in desc["type_hashes"] if h["type_name"] == "tf2_msgs/msg/TFMessage")
    assert own == get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
