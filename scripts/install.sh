#!/usr/bin/env bash
# Install elasticfog and every dependency at the exact versions of the lock (hash-checked),
# into the active virtual environment. The project itself goes in editable, without resolving
# anything again, so the lock alone decides every version.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install -q --require-hashes -r requirements/dev.lock
python -m pip install -q --no-deps --no-build-isolation -e .
