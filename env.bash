# ROS by hand in this shell, after `make setup`:   source env.bash
#
# Sources this package's catkin workspace, which make setup builds outside the
# package tree (the Makefile's AMBOTS_WS, default ~/.cache/ambots/ws-<hash>):
# Debian's ROS 1, the package on ROS_PACKAGE_PATH (rosrun, roslaunch, rostest),
# and .venv/bin first on PATH (its catkin env hook).
_ambots_root=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
_ambots_ws=$(make -s --no-print-directory -C "$_ambots_root" ws-path)
if [ -f "$_ambots_ws/devel/setup.bash" ]; then
  # shellcheck disable=SC1091
  source "$_ambots_ws/devel/setup.bash"
else
  echo "env.bash: no workspace at $_ambots_ws: run 'make setup' in $_ambots_root first" >&2
fi
unset _ambots_root _ambots_ws
