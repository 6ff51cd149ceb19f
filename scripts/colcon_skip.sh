#!/usr/bin/env bash
# Prints the colcon arguments that skip the workspace's stand-ins for packages the environment already has:
# src/tf2_msgs (for the PyPI-wheel ROS, which ships no tf2_msgs) is skipped when a tf2_msgs outside this
# workspace is on AMENT_PREFIX_PATH (a system ROS 2 Jazzy sourced by scripts/env.sh). `make build` uses it.
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
IFS=: read -r -a prefixes <<< "${AMENT_PREFIX_PATH:-}"
for p in "${prefixes[@]}"; do
  case "$p" in "" | "$root"/install | "$root"/install/*) continue ;; esac
  if [ -f "$p/share/ament_index/resource_index/packages/tf2_msgs" ]; then
    echo "--packages-skip tf2_msgs"
    exit 0
  fi
done
