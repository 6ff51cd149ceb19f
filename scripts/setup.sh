#!/usr/bin/env bash
# fullperc setup: makes .venv ready to build and run the workspace.
#
#  * With a system ROS 2 Jazzy (/opt/ros/jazzy/setup.bash) the venv is created with
#    --system-site-packages on top of it and gets only our Python dependencies.
#  * Otherwise ROS 2 Jazzy comes from exact-pinned PyPI wheels (requirements/ros-jazzy.txt).
#  * Everything is installed from requirements/lock-<tag>.txt (exact versions, the whole
#    closure) when a lock for this interpreter exists, else from the loose lists.
#  * Idempotent: a stamp records the hash of the inputs; with nothing changed it exits at once.
#
# Environment: PYTHON (interpreter to build the venv with, default python3), VENV (default .venv),
#              FULLPERC_USE_SYSTEM_ROS=0 to ignore /opt/ros/jazzy, FULLPERC_REQUIREMENTS (dir, tests).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
PYTHON="${PYTHON:-python3}"
VENV="${VENV:-.venv}"
ROS_SETUP=/opt/ros/jazzy/setup.bash
REQ="${FULLPERC_REQUIREMENTS:-requirements}"   # overridable for the setup tests

die() { echo "fullperc setup: ERROR: $*" >&2; exit 1; }

command -v "$PYTHON" >/dev/null 2>&1 || die "interpreter '$PYTHON' not found (set PYTHON=...)"
pyver="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')" \
  || die "'$PYTHON' does not run"
case "$pyver" in 3.1[0-9]) ;; *) die "Python >= 3.10 required, '$PYTHON' is $pyver" ;; esac
tag="cp${pyver/./}"

mode=wheels
if [ -f "$ROS_SETUP" ] && [ "${FULLPERC_USE_SYSTEM_ROS:-1}" != 0 ]; then mode=system; fi

lock="$REQ/lock-$tag.txt"
inputs=("$REQ/ros-jazzy.txt" "$REQ/python.txt" scripts/setup.sh)
[ -f "$lock" ] && inputs+=("$lock")
stamp_want="$mode $pyver $(cat "${inputs[@]}" | sha256sum | cut -c1-16)"
stamp_file="$VENV/.fullperc-setup"
ament_marker="$VENV/local_setup.sh"   # wheels only, see mark_ament_prefix below
if [ -f "$stamp_file" ] && [ "$(cat "$stamp_file")" = "$stamp_want" ] && [ -x "$VENV/bin/python" ] \
   && { [ "$mode" = system ] || [ -f "$ament_marker" ]; }; then
  echo "fullperc setup: up to date ($mode, Python $pyver, $VENV)"
  exit 0
fi

if [ -d "$VENV" ] && ! "$VENV/bin/python" -c 'import sys; sys.exit(0 if "%d.%d" % sys.version_info[:2] == "'"$pyver"'" else 1)' 2>/dev/null; then
  echo "fullperc setup: $VENV was made with another Python; recreating it (and build/ install/)"
  rm -rf "$VENV" build install log
fi

echo "fullperc setup: mode=$mode python=$pyver venv=$VENV"
if [ "$mode" = system ]; then
  # shellcheck disable=SC1090
  set +u; source "$ROS_SETUP"; set -u
  [ -d "$VENV" ] || "$PYTHON" -m venv --system-site-packages "$VENV" || die "could not create $VENV"
else
  [ -d "$VENV" ] || "$PYTHON" -m venv "$VENV" || die "could not create $VENV (is python$pyver-venv installed?)"
fi

pip=("$VENV/bin/python" -m pip --disable-pip-version-check)

install_one_by_one() {
  # A failed bulk install names the package only deep in pip's output; retrying each
  # requirement on its own pins the failure to one line the user can act on.
  local file="$1" line
  while IFS= read -r line; do
    line="${line%%#*}"; line="$(echo "$line" | xargs)"
    [ -n "$line" ] || continue
    "${pip[@]}" install -q "$line" >/dev/null 2>&1 \
      || die "could not install '$line' (from $file). Check the pin exists for Python $pyver: $VENV/bin/pip install '$line'"
  done < "$file"
}

install_file() {
  local file="$1"
  if ! "${pip[@]}" install -q -r "$file"; then
    echo "fullperc setup: bulk install from $file failed; finding the package that fails ..." >&2
    install_one_by_one "$file"
  fi
}

if [ -f "$lock" ]; then
  if [ "$mode" = system ]; then
    grep -v -E '^ros-|^colcon' "$lock" > "$VENV/.lock-nonros.txt"
    install_file "$VENV/.lock-nonros.txt"
  else
    install_file "$lock"
  fi
else
  echo "fullperc setup: no $lock; installing from the loose lists (run 'make lock' to pin them)"
  [ "$mode" = system ] || install_file "$REQ/ros-jazzy.txt"
  install_file "$REQ/python.txt"
fi

# Check that what the build needs really imports, naming what does not.
check='import numpy, scipy, yaml, rosbags, mcap, serial, matplotlib, pinocchio'
[ "$mode" = wheels ] && check="$check, rclpy, rosidl_adapter, ament_package, colcon_core"
"$VENV/bin/python" -c "$check" 2>"$VENV/.import-error" \
  || die "installed packages do not import: $(tail -1 "$VENV/.import-error")"
if [ "$mode" = wheels ]; then
  [ -f "$VENV/share/std_msgs/cmake/std_msgsConfig.cmake" ] || die "ros-jazzy-common-interfaces is missing share/std_msgs/cmake"
fi

# The wheels put share/ament_index into the venv root, and scripts/env.sh adds that root to AMENT_PREFIX_PATH.
# colcon accepts a prefix there only if it holds a local_setup.* file (else it warns on every build that the path
# "doesn't contain any 'local_setup.*' files"), and the install/setup.* it generates then source the prefix's
# local_setup.<shell>. The venv needs nothing sourced (env.sh sets its paths), so these files only mark it.
mark_ament_prefix() {
  local ext
  for ext in sh bash zsh ps1; do
    printf '%s\n' "# fullperc (scripts/setup.sh): marks this venv as an ament prefix for colcon; nothing to set up." \
      "# The ROS 2 wheels installed share/ament_index here; scripts/env.sh puts it on AMENT_PREFIX_PATH." \
      > "$VENV/local_setup.$ext"
  done
}
if [ "$mode" = wheels ]; then mark_ament_prefix; fi

echo "$stamp_want" > "$stamp_file"
echo "fullperc setup: done"
