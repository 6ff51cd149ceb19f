"""Bring-up on real hardware for a full ROS 2 Jazzy install: `ros2 launch fullperc_eval bringup.launch.py ...`.

Same processes, parameters and arguments as config/bringup_graph.yaml (which the supervisor runs where `launch` is not
installed; that file documents every argument); test_launch_matches_graph.py keeps the two in step. NDI tracker,
NOKOV motion capture, optionally the Diana 7 (with_diana:=true), fusion_node and margin_node; no simulator. The
arguments without a default are required: the device addresses, the tool ROMs (your tool maker's: fullperc's ROMs are
synthetic, for its emulator only), the body and target names and the fusion parameter file, e.g.

    ros2 launch fullperc_eval bringup.launch.py ndi_address:=P9-01234.local "tools:=[tool, base]" \\
        "tool_roms:=[$HOME/roms/tool.rom, $HOME/roms/base.rom]" nokov_server:=10.1.1.198 \\
        nokov_sdk:=$HOME/nokov/libnokov_sdk.so "bodies:=[base, tool]" "targets:=[tool]" \\
        fusion_params:=$HOME/or1/fusion.yaml

Unlike the supervisor, launch has no readiness gates: the drivers start with fusion_node, which then may miss their
first samples (it calibrates from the ones it gets). Steps, a healthy start and a symptom -> fix table:
docs/hardware.md.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration as C
from launch_ros.actions import Node

# name -> default; None: required (bringup_graph.yaml's placeholders without a `vars` default). diana_library is
# needed only with with_diana:=true (the graph then requires it; launch requires a declared argument always, so '')
ARGUMENTS = {
    "ndi_address": None, "tools": None, "tool_roms": None, "nokov_server": None, "nokov_sdk": None, "bodies": None,
    "targets": None, "fusion_params": None, "diana_library": "",
    "ndi_transport": "tcp", "ndi_port": "8765", "ndi_baud": "115200", "tool_priorities": "['']",
    "ndi_latency_s": "0.0", "sdk_timestamp_unit_ns": "1000000", "sdk_latency_unit_s": "1.0",
    "sdk_valid_flag_mask": "0", "layout_file": "''", "with_diana": "false", "robot_ip": "192.168.10.75",
}


def generate_launch_description():
    args = [DeclareLaunchArgument(n) if v is None else DeclareLaunchArgument(n, default_value=v)
            for n, v in ARGUMENTS.items()]
    # launch_ros reads each substituted value as YAML: "[tool, base]" becomes a list, "8765" an integer
    fusion = Node(package="fullperc_fusion", executable="fusion_node", name="fusion_node",
                  parameters=[C("fusion_params"), {"targets": C("targets")}],
                  sigterm_timeout="30")   # it fuses what its input queues hold at SIGINT (the graph's grace)
    margin = Node(package="fullperc_fusion", executable="margin_node", name="margin_node",
                  parameters=[{"targets": C("targets"), "layout_file": C("layout_file")}])
    omc = Node(package="fullperc_drivers", executable="omc_driver", name="omc_driver",
               parameters=[{"backend": "nokov_sdk", "server": C("nokov_server"), "sdk_library": C("nokov_sdk"),
                            "bodies": C("bodies"), "sdk_timestamp_unit_ns": C("sdk_timestamp_unit_ns"),
                            "sdk_latency_unit_s": C("sdk_latency_unit_s"),
                            "sdk_valid_flag_mask": C("sdk_valid_flag_mask")}])
    diana = Node(package="fullperc_drivers", executable="diana_state", name="diana_state",
                 condition=IfCondition(C("with_diana")),
                 parameters=[{"backend": "diana_api", "api_library": C("diana_library"), "robot_ip": C("robot_ip")}])
    # one address for either transport: the driver reads `host` for tcp and `serial_device` for serial
    ndi = Node(package="fullperc_drivers", executable="ndi_driver", name="ndi_driver",
               parameters=[{"transport": C("ndi_transport"), "host": C("ndi_address"), "port": C("ndi_port"),
                            "serial_device": C("ndi_address"), "baud": C("ndi_baud"), "tools": C("tools"),
                            "tool_roms": C("tool_roms"), "tool_priorities": C("tool_priorities"),
                            "device_latency_s": C("ndi_latency_s")}])
    return LaunchDescription([*args, fusion, margin, omc, diana, ndi])
