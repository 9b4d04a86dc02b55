# Source me (bash or zsh): `source env.sh`. The project's environment: the virtual environment, the
# ROS 2 Jazzy wheels in it, and the ros_ws overlay built by setup.sh. DDS discovery stays on this
# machine unless you set ROS_AUTOMATIC_DISCOVERY_RANGE yourself (SUBNET to reach a robot).
_ad_root="$(cd "$(dirname "${BASH_SOURCE[0]:-${(%):-%x}}")" && pwd)"
if [ ! -f "$_ad_root/ros_ws/install/setup.bash" ]; then
    echo "env.sh: ros_ws is not built yet: run $_ad_root/setup.sh first" >&2
    unset _ad_root _ad_venv _ad_nounset
    return 1 2>/dev/null || exit 1
fi
# The venv's and colcon's scripts read unset variables: `set -u` in the calling shell is lifted meanwhile.
case $- in *u*) _ad_nounset=1; set +u ;; *) _ad_nounset= ;; esac
_ad_venv="${VENV:-$(cat "$_ad_root/ros_ws/install/.ad-venv" 2>/dev/null || echo "$_ad_root/.venv")}"
if ! . "$_ad_venv/bin/activate" || ! { if [ -n "${ZSH_VERSION:-}" ]; then . "$_ad_root/ros_ws/install/setup.zsh"
                                        else . "$_ad_root/ros_ws/install/setup.bash"; fi; }; then
    echo "env.sh: the environment is incomplete (venv $_ad_venv): run $_ad_root/setup.sh again" >&2
    command -v deactivate >/dev/null && deactivate  # no half-set environment
    [ -n "$_ad_nounset" ] && set -u
    unset _ad_root _ad_venv _ad_nounset
    return 1 2>/dev/null || exit 1
fi
[ -n "$_ad_nounset" ] && set -u
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export AD_ROOT="$_ad_root"
# `python -m training` (the training package at the repository root) from any directory.
case ":${PYTHONPATH:-}:" in *":$_ad_root:"*) ;; *) export PYTHONPATH="$_ad_root${PYTHONPATH:+:$PYTHONPATH}" ;; esac
unset _ad_root _ad_venv _ad_nounset
