#!/usr/bin/env bash
# Create .venv/ at the repository root and install the engine, the service and the test tools.
# Installs from Debian's packages what is missing (needs root or sudo): Mesa's EGL driver and
# glvnd's OpenGL library,
# redis-server (the embedded broker of vehicle-pose-service), and for the tests chromium (the
# admin page in a real browser) and postgresql (the database of the scaled-out set-up).
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libEGL_mesa.so' || need_apt+=(libegl-mesa0 libegl1 libgl1-mesa-dri libgbm1)
# The GL calls made through ctypes (the exterior pass's lanes, the layered draws) load libOpenGL.
ldconfig -p 2>/dev/null | grep -q 'libOpenGL.so.0' || need_apt+=(libopengl0)
command -v redis-server >/dev/null || need_apt+=(redis-server)
command -v chromium >/dev/null || need_apt+=(chromium)
ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || need_apt+=(postgresql)
if [ ${#need_apt[@]} -gt 0 ]; then
  sudo_cmd=""
  [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[service,test]'
# numba compiles its kernels on first use and keeps them beside the sources: preparing one
# shipped model and registering the example photo with no hint (the search that uses every
# kernel), into a throw-away cache, spares a user's first preparation the 4-5 s and first
# registration the 15 s of compiling them.
warm="$(mktemp -d)"
if .venv/bin/vehicle-pose prepare sedan --cache-dir "$warm" >/dev/null 2>&1; then
  .venv/bin/vehicle-pose register examples/sedan.jpg --model sedan --cache-dir "$warm" --out "$warm/result.json" \
    >/dev/null 2>&1 || echo "note: the example did not register now; the registration's kernels compile on first use"
else
  echo "note: could not prepare the sedan now (no OpenGL?); the kernels compile on first use"
fi
rm -rf "$warm"
echo "ready: .venv/bin/vehicle-pose"
