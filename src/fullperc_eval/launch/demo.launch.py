"""The simulated-OR demo graph for a full ROS 2 Jazzy install: `ros2 launch fullperc_eval demo.launch.py`.

Same processes and parameters as config/demo_graph.yaml (which `make demo` runs with fullperc's own
supervisor where `launch` is not available); test_launch_matches_graph.py keeps the two in step.
Arguments: task (P-B-G-P), seed (0), speed (1.0), profile (paper | spec), calibration_file ('' = fusion_node
calibrates itself), out (demo_out/launch), ports omc_port (3883), diana_port (3884), vega_port (8765). After the
simulator finishes, the whole launch shuts down; evaluate
the bag with `ros2 run fullperc_eval evaluate <out>/bag --calibration <out>/calibration.yaml` (the hand-held
`instrument` needs its truth: merge <out>/truth into the bag with fullperc_eval.sim.dataset.merge_bag, then
`--target instrument`).
Unlike `make demo`, the launch file does not give fusion_node `tf.diana_base` (the arm's base in `base`, from the
simulator's task plan): add `-p tf.diana_base:=[...]` from `python -c "from fullperc_eval.graph.demo import
sim_diana_base; print(sim_diana_base('P-B-G-P', 0, 'paper'))"` to hang the arm's tree under `base` in RViz.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, ExecuteProcess, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration as C
from launch.substitutions import PathJoinSubstitution
from launch_ros.actions import Node

RECORD_TOPICS = [
    "/omc/base/pose", "/omc/ots_rig/pose", "/omc/tool/pose", "/omc/base/quality", "/omc/ots_rig/quality",
    "/omc/tool/quality", "/ots/tool/pose", "/ots/base/pose", "/ots/tool/quality", "/ots/base/quality",
    "/diana/joint_states", "/diana/flange_pose", "/fullperc/tool/pose", "/fullperc/tool/pose_cov",
    "/fullperc/tool/status", "/fullperc/tool/ckf/pose", "/fullperc/tool/bkf/pose", "/fullperc/tool/kf/pose",
    "/fullperc/tool/omc/pose", "/fullperc/tool/region", "/diagnostics", "/tf", "/tf_static",
    "/omc/instrument/pose", "/omc/instrument/quality", "/ots/instrument/pose", "/ots/instrument/quality",
    "/fullperc/instrument/pose", "/fullperc/instrument/pose_cov", "/fullperc/instrument/status",
    "/fullperc/instrument/ckf/pose", "/fullperc/instrument/bkf/pose", "/fullperc/instrument/kf/pose",
    "/fullperc/instrument/omc/pose", "/fullperc/instrument/region",
    # the primary filter's estimates once final (fusion_node's processing on arrival): evaluate --live
    "/fullperc/tool/final", "/fullperc/instrument/final",
]


def generate_launch_description():
    args = [DeclareLaunchArgument(n, default_value=v) for n, v in (
        ("task", "P-B-G-P"), ("seed", "0"), ("speed", "1.0"), ("profile", "paper"), ("calibration_file", ""),
        ("out", "demo_out/launch"),
        ("omc_port", "3883"), ("diana_port", "3884"), ("vega_port", "8765"))]
    out = C("out")
    record = Node(package="fullperc_eval", executable="record", name="record",
                  arguments=["-o", PathJoinSubstitution([out, "bag"]), "--topics", *RECORD_TOPICS])
    fusion = Node(package="fullperc_fusion", executable="fusion_node", name="fusion_node",
                  parameters=[{"filter": "cbkf", "filters": ["ckf", "bkf", "kf", "omc"],
                               "calibration_file": C("calibration_file"), "targets": ["tool", "instrument"],
                               "instrument.motion": "hand", "qos_depth": 10000, "history": 3.0,
                               "reorder_delay": 2.5, "inputs": "frames"}],   # demo_graph.yaml says why
                  # at SIGINT it fuses what its input queues still hold (demo_graph.yaml's grace)
                  sigterm_timeout="30")
    margin = Node(package="fullperc_fusion", executable="margin_node", name="margin_node",
                  parameters=[{"targets": ["tool", "instrument"]}])
    omc = Node(package="fullperc_drivers", executable="omc_driver", name="omc_driver",
               parameters=[{"backend": "stream", "stream_port": C("omc_port"),
                            "bodies": ["base", "ots_rig", "tool", "instrument"]}])
    diana = Node(package="fullperc_drivers", executable="diana_state", name="diana_state",
                 parameters=[{"backend": "stream", "stream_port": C("diana_port")}])
    # launch has no readiness gates: the task starts once ndi_driver tracks plus 2 s, which usually covers DDS
    # discovery; the supervisor graph (demo_graph.yaml) waits for the drivers' matched subscribers instead.
    sim = ExecuteProcess(
        cmd=["ros2", "run", "fullperc_eval", "sim", "--task", C("task"), "--seed", C("seed"), "--speed", C("speed"),
             "--omc-addr", ["127.0.0.1:", C("omc_port")], "--diana-addr", ["127.0.0.1:", C("diana_port")],
             "--vega-port", C("vega_port"), "--start-when-tracking", "120", "--start-delay", "2.0",
             "--calibration-out", PathJoinSubstitution([out, "calibration.yaml"]), "--profile", C("profile"),
             "--truth-out", PathJoinSubstitution([out, "truth"])],
        name="sim", output="screen")
    ndi = Node(package="fullperc_drivers", executable="ndi_driver", name="ndi_driver",
               parameters=[{"transport": "tcp", "host": "127.0.0.1", "port": C("vega_port"),
                            "tools": ["tool", "base", "instrument"],
                            "tool_roms": ["emulator_roms/tool.rom", "emulator_roms/base.rom",
                                          "emulator_roms/tool_d.rom"]}])
    done = RegisterEventHandler(OnProcessExit(target_action=sim, on_exit=[EmitEvent(event=Shutdown())]))
    return LaunchDescription([*args, record, fusion, margin, omc, diana, sim, ndi, done])
