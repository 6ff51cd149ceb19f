# Source this file (bash) to get the fullperc environment: the venv, ROS 2 (system or wheels),
# and the built workspace. `make` sources it for every recipe; users can too:
#     source scripts/env.sh && install/fullperc_fusion/lib/fullperc_fusion/fusion_node
_fp_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_fp_venv="${VENV:-.venv}"
case "$_fp_venv" in /*) ;; *) _fp_venv="$_fp_root/$_fp_venv" ;; esac
_fp_nounset=0; case $- in *u*) _fp_nounset=1; set +u ;; esac

if [ -f /opt/ros/jazzy/setup.bash ] && [ "${FULLPERC_USE_SYSTEM_ROS:-1}" != 0 ]; then
  source /opt/ros/jazzy/setup.bash
  _fp_ros_prefix=""
else
  # The wheels install share/ament_index into the venv root but ship no setup files, so
  # nothing sets these for them (reference/bags_ros2.md §6.4).
  _fp_ros_prefix="$_fp_venv"
fi
export VIRTUAL_ENV="$_fp_venv"
export PATH="$_fp_venv/bin:$PATH"
export Python3_EXECUTABLE="$_fp_venv/bin/python3"
if [ -f "$_fp_root/install/setup.bash" ]; then
  COLCON_TRACE= AMENT_TRACE_SETUP_FILES= source "$_fp_root/install/setup.bash" 2>/dev/null
fi
if [ -n "$_fp_ros_prefix" ]; then
  case ":${AMENT_PREFIX_PATH:-}:" in *":$_fp_ros_prefix:"*) ;; *)
    export AMENT_PREFIX_PATH="${AMENT_PREFIX_PATH:+$AMENT_PREFIX_PATH:}$_fp_ros_prefix" ;; esac
  case ":${CMAKE_PREFIX_PATH:-}:" in *":$_fp_ros_prefix:"*) ;; *)
    export CMAKE_PREFIX_PATH="${CMAKE_PREFIX_PATH:+$CMAKE_PREFIX_PATH:}$_fp_ros_prefix" ;; esac
fi
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
export FULLPERC_ROOT="$_fp_root"
export MPLBACKEND="${MPLBACKEND:-Agg}"
[ "$_fp_nounset" = 1 ] && set -u
unset _fp_root _fp_venv _fp_ros_prefix _fp_nounset
