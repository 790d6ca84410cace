#!/usr/bin/env bash
# One entry point that sets everything up, then runs the demo or the tests.
#   bash tools/run.sh demo    # render a synthetic rig, calibrate it, write the report
#   bash tools/run.sh test    # the test suite (CI: .ci/run calls this)
#   bash tools/run.sh <command> ...   # any other rgbd-calib command
# Creates .venv (Python 3.11+), installs the pinned packages of requirements.lock and the
# package itself, and Debian's libusb-1.0-0 (needed by open3d and pyrealsense2) when missing.
# The environment lives in the repository; `demo` and the other commands run in the folder
# the script is called from (their relative paths and outputs are the caller's), `test` in
# the repository.
set -euo pipefail
CALLER=$(pwd)
cd "$(dirname "$0")/.."
ROOT=$(pwd)
VENV="${RGBD_CALIB_VENV:-$ROOT/.venv}"
case "$VENV" in /*) ;; *) VENV="$ROOT/$VENV" ;; esac  # a relative one: from the repository

# ldconfig lives in /sbin, which a user's (or a CI job's) PATH may leave out
LDCONFIG="$(command -v ldconfig || echo /sbin/ldconfig)"
# the cache read whole before grep looks (grep -q stops at the first match, ldconfig then dies of
# SIGPIPE and pipefail turned a library that is there into one that is missing, ~4 % of calls)
need_libusb() {
  local cache
  cache=$("$LDCONFIG" -p 2>/dev/null || true)
  [[ "$cache" != *libusb-1.0.so.0* ]]
}
if need_libusb; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "installing libusb-1.0-0 (needed by open3d and pyrealsense2) ..." >&2
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0) >/dev/null \
      || { echo "error: apt-get install libusb-1.0-0 failed; install it and re-run" >&2; exit 1; }
  else
    echo "error: libusb-1.0-0 is missing; run 'sudo apt-get install libusb-1.0-0' and re-run" >&2
    exit 1
  fi
fi

PY=""
for c in python3.13 python3.12 python3.11 python3; do
  if command -v "$c" >/dev/null && "$c" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
    PY=$c; break
  fi
done
[ -n "$PY" ] || { echo "error: Python 3.11+ not found; install python3 (>= 3.11) and re-run" >&2; exit 1; }

STAMP="$VENV/.rgbd-calib-stamp"
WANT=$(cat pyproject.toml requirements.lock | sha256sum | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  echo "setting up $VENV (pinned packages from requirements.lock) ..." >&2
  # an existing environment is updated with its own interpreter: re-running `venv` over it
  # with another Python (e.g. a system one without ensurepip) rewrites its pyvenv.cfg and
  # breaks it before failing
  if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV" 2>/dev/null || {
      echo "error: '$PY -m venv' failed; run 'sudo apt-get install python3-venv' and re-run" >&2; exit 1; }
  fi
  "$VENV/bin/python" -m pip install -q --upgrade pip 2>&1 | grep -v "is ignored: it is neither" >&2 || true
  # kiss-icp asks for typer[all], an extra typer no longer has (rich is pinned here anyway):
  # pip's one-line warning about it is noise, as are the index locations it ignores
  "$VENV/bin/python" -m pip install -q -r requirements.lock 2>&1 \
    | grep -v -e "is ignored: it is neither" -e "does not provide the extra 'all'" >&2 || true
  # setuptools' "Editable installation" BuildBackendWarning is advice for package authors
  PYTHONWARNINGS=ignore "$VENV/bin/python" -m pip install -q --no-deps -e ".[dev,ros,dask]" 2>&1 \
    | grep -v "is ignored: it is neither" >&2 || true
  "$VENV/bin/python" -c "import rgbd_calib, cv2, gtsam, open3d, pyrealsense2" \
    || { echo "error: the environment in $VENV is incomplete; delete it and re-run" >&2; exit 1; }
  echo "$WANT" > "$STAMP"
fi

cmd="${1:-demo}"; shift || true
case "$cmd" in
  demo)
    cd "$CALLER"
    exec "$VENV/bin/rgbd-calib" demo "$@" ;;
  test)
    # The report's browser test drives Debian's Chromium; install it when we can (root + apt),
    # otherwise that one test skips with its reason.
    if ! command -v chromium >/dev/null && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      echo "installing chromium (for the report's browser test) ..." >&2
      (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) >/dev/null \
        || echo "warning: could not install chromium; the browser test will be skipped" >&2
    fi
    # Default suite: everything not marked slow. RGBD_CALIB_SLOW=1 adds the slow tier.
    marker="not slow"
    [ "${RGBD_CALIB_SLOW:-0}" = 1 ] && marker=""
    # One pytest worker per core, at most 4 (each test may render and calibrate with 2
    # processes of its own); a file's tests stay on one worker, so its fixtures are built
    # once. RGBD_CALIB_TEST_WORKERS=0 runs in this one process.
    cores=$(nproc 2>/dev/null || echo 2)
    workers="${RGBD_CALIB_TEST_WORKERS:-$(( cores < 4 ? cores : 4 ))}"
    set +e
    "$VENV/bin/python" -m pytest -m "$marker" -n "$workers" --dist loadfile "$@"
    rc=$?
    set -e
    if [ $rc -eq 5 ]; then echo "error: pytest collected no tests" >&2; exit 1; fi
    exit $rc ;;
  *)
    cd "$CALLER"
    exec "$VENV/bin/rgbd-calib" "$cmd" "$@" ;;
esac
