# Source this file to enter the workspace environment (the venv + the colcon install space).
# Used by ./bike, the Makefile and the tests; safe to source more than once.
_bike_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_bike_venv=${BIKE_VENV:-$_bike_root/.venv}
# Another checkout's environment already entered in this shell (a second clone, CI's 3.12
# copy): drop its paths first, or its install space would shadow this one's.
if [ -n "${BIKE_ROOT:-}" ] && [ "$BIKE_ROOT" != "$_bike_root" ]; then
  for _bike_var in PATH PYTHONPATH LD_LIBRARY_PATH AMENT_PREFIX_PATH CMAKE_PREFIX_PATH COLCON_PREFIX_PATH; do
    _bike_kept=$(printf '%s' "${!_bike_var:-}" | tr ':' '\n' | { grep -v -F -e "$BIKE_ROOT/" || true; } | paste -s -d ':' -)
    if [ -n "$_bike_kept" ]; then export "$_bike_var=$_bike_kept"; else unset "$_bike_var"; fi
  done
  unset _bike_var _bike_kept
fi
export AMENT_PREFIX_PATH="$_bike_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
# shellcheck disable=SC1091
source "$_bike_venv/bin/activate"
# shellcheck disable=SC1091
source "$_bike_root/install/setup.bash"
# Security default: DDS discovery stays on this host unless the user configures otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
# Fast DDS: reliable writers ask for acknowledgments every 100 ms, not every 3 s (config/fastdds.xml)
export FASTRTPS_DEFAULT_PROFILES_FILE=${FASTRTPS_DEFAULT_PROFILES_FILE:-$_bike_root/config/fastdds.xml}
export BIKE_ROOT="$_bike_root"
export MPLBACKEND=${MPLBACKEND:-Agg}
