#!/usr/bin/env bash
# Refresh the lock: newest versions within pyproject's ranges, with hashes (pip-tools).
# torch stays at the CPU build pinned in pyproject. Takes a few minutes (it fetches every hash).
set -euo pipefail
cd "$(dirname "$0")/.."
CUSTOM_COMPILE_COMMAND="bash scripts/lock.sh" python -m piptools compile --upgrade --extra dev --generate-hashes --allow-unsafe --strip-extras \
    --no-emit-index-url --no-emit-find-links \
    -o requirements/dev.lock pyproject.toml
