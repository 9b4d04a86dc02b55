# Source me (bash or zsh): `source env.sh`. The project's environment: the virtual environment, the
# ROS 2 Jazzy wheels in it, and the ros_ws overlay built by setup.sh. DDS discovery stays on this
# machine unless you set ROS_AUTOMATIC_DISCOVERY_RANGE yourself (SUBNET to reach a robot).
_ad_root="$(cd "$(dirname "${BASH_SOURCE[0]:-${(%):-%x}}")" && pwd)"
if [ ! -f "$_ad_root/ros_ws/install/setup.bash" ]; then
    echo "env.sh: ros_ws is not built yet: run $_ad_root/setup.sh first" >&2
    unset _ad_root
    return 1 2>/dev/null || exit 1
fi
. "${VENV:-$(cat "$_ad_root/ros_ws/install/.ad-venv" 2>/dev/null || echo "$_ad_root/.venv")}/bin/activate"
if [ -n "${ZSH_VERSION:-}" ]; then . "$_ad_root/ros_ws/install/setup.zsh"; else . "$_ad_root/ros_ws/install/setup.bash"; fi
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export AD_ROOT="$_ad_root"
# `python -m training` (the training package at the repository root) from any directory.
case ":${PYTHONPATH:-}:" in *":$_ad_root:"*) ;; *) export PYTHONPATH="$_ad_root${PYTHONPATH:+:$PYTHONPATH}" ;; esac
unset _ad_root
