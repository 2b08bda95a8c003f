#!/usr/bin/env bash
# Drift check: the unit tier against the newest versions the index serves (no lock, nothing
# pinned). It warns and never fails, so a new upstream release is seen before a lock refresh
# takes it in. The integration and e2e tiers are left to the locked run: with the ROS 2,
# results and metrics tests the whole CI run must stay within its 20 minutes on 2 cores.
set -uo pipefail
cd "$(dirname "$0")/.."
venv="$(mktemp -d)/drift"
python3 -m venv "$venv"
# shellcheck disable=SC1091
source "$venv/bin/activate"
if ! python -m pip install -q --upgrade pip -e ".[dev]" >"$venv.log" 2>&1; then
    echo "WARNING drift: install of the newest versions failed:"; tail -20 "$venv.log"; exit 0
fi
newer=$(python -m pip freeze --exclude-editable | grep -vxFf <(grep -oE '^[A-Za-z0-9_.-]+==[^ ]+' requirements/dev.lock) || true)
echo "drift: versions newer than the lock:"; echo "${newer:-  (none)}" | sed 's/^/  /'
if python -m pytest -q -p no:cacheprovider tests/unit >"$venv.log" 2>&1; then
    echo "drift: the unit tier passes on the newest versions"
else
    echo "WARNING drift: tests fail on the newest versions (the locked run below decides):"
    grep -E "^(FAILED|ERROR)" "$venv.log" | head -30
    tail -1 "$venv.log" | sed 's/^=*/  /'
fi
deactivate
exit 0
