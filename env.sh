# Source me (bash or zsh): `source env.sh`. The project's environment: the virtual environment, the
# ROS 2 Jazzy wheels in it, and the ros_ws overlay built by setup.sh. DDS discovery stays on this
# machine unless you set ROS_AUTOMATIC_DISCOVERY_RANGE yourself (SUBNET to reach a robot).
_ad_root="$(cd "$(dirname "${BASH_SOURCE[0]:-${(%):-%x}}")" && pwd)"
if [ ! -f "$_ad_root/ros_ws/install/setup.bash" ]; then
    echo "env.sh: ros_ws is not built yet: run $_ad_root/setup.sh first" >&2
    unset _ad_root _ad_venv _ad_nounset
    return 1 2>/dev/null || exit 1
fi
_ad_venv="${VENV:-$(cat "$_ad_root/ros_ws/install/.ad-venv" 2>/dev/null || echo "$_ad_root/.venv")}"
# A checkout moved or copied to another path keeps its old path in what setup.sh made: colcon's install tree
# runs the code of the checkout it was built in (its links and egg-links lead to that ros_ws/build, its
# executables' shebangs to that venv) and a venv's scripts name the path it was made at. Sourced as it is, it
# ran the other checkout's code without a word while that checkout still existed. Nothing is sourced then.
# (-ef, not string equality: the checkout may be reached through a symbolic link.)
_ad_moved=
_ad_made_at="$(sed -n 's/^_colcon_prefix_sh_COLCON_CURRENT_PREFIX="\(.*\)"$/\1/p' "$_ad_root/ros_ws/install/local_setup.sh" 2>/dev/null | head -n 1 || true)"
if [ -n "$_ad_made_at" ] && ! [ "$_ad_made_at" -ef "$_ad_root/ros_ws/install" ]; then
    _ad_moved="ros_ws/install was built in ${_ad_made_at%/ros_ws/install}, not in this checkout"
else
    # (not a command substitution: newer Pythons' activate first sets it to $(cygpath PATH), for Cygwin)
    _ad_made_at="$(sed -nE "s/^ *(export +)?VIRTUAL_ENV=[\"']?([^\"'\$]*)[\"']?$/\2/p" "$_ad_venv/bin/activate" 2>/dev/null | head -n 1 || true)"
    if [ -n "$_ad_made_at" ] && ! [ "$_ad_made_at" -ef "$_ad_venv" ]; then
        _ad_moved="the venv $_ad_venv was made at $_ad_made_at"
    fi
fi
if [ -n "$_ad_moved" ]; then
    echo "env.sh: $_ad_moved (moved or copied?), and would run the code there or fail: run $_ad_root/setup.sh again, which makes it anew here" >&2
    unset _ad_root _ad_venv _ad_nounset _ad_moved _ad_made_at
    return 1 2>/dev/null || exit 1
fi
unset _ad_moved _ad_made_at
# The venv's and colcon's scripts read unset variables: `set -u` in the calling shell is lifted meanwhile.
case $- in *u*) _ad_nounset=1; set +u ;; *) _ad_nounset= ;; esac
if ! . "$_ad_venv/bin/activate" || ! { if [ -n "${ZSH_VERSION:-}" ]; then . "$_ad_root/ros_ws/install/setup.zsh"
                                        else . "$_ad_root/ros_ws/install/setup.bash"; fi; }; then
    echo "env.sh: the environment is incomplete (venv $_ad_venv): run $_ad_root/setup.sh again" >&2
    typeset -f deactivate >/dev/null 2>&1 && deactivate  # no half-set environment (the venv's function, not pyenv's command)
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
