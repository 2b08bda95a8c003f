"""Check that the locks install on every platform and Python they claim, without that hardware.

For each lock, CPU architecture (Linux x86_64 and aarch64 with glibc 2.28 or newer) and
Python (3.10 to 3.13), the lock's environment markers are evaluated for that target (pip would
evaluate them for the Python running it), and pip downloads exactly the pinned files, wheels only,
hash-checked, from the public index alone (local pip configuration ignored):

    python scripts/lock_check.py [--lock requirements/runtime.lock ...] [--python 3.10 ...]

Prints one line per combination; exits 1 if any combination fails (those NOT_SERVED lists are
reported as n/a).
Downloads a few GB the first time (pip's cache keeps them for the next run).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

try:
    from packaging.requirements import Requirement
except ImportError:  # pip vendors the same library
    from pip._vendor.packaging.requirements import Requirement  # type: ignore[no-redef]

ROOT = Path(__file__).resolve().parents[1]
LOCKS = ("requirements/runtime.lock", "requirements/dev.lock", "requirements/gpu.lock")
PYTHONS = ("3.10", "3.11", "3.12", "3.13")
ARCHES = ("x86_64", "aarch64")
# Combinations the public index cannot serve, and why: checked still, reported, not failed.
NOT_SERVED = {
    ("requirements/gpu.lock", "aarch64"): "onnxruntime-gpu has no Linux aarch64 wheels on the "
    "public index (Jetson: NVIDIA's JetPack builds of onnxruntime-gpu)",
}
# The newest glibc a target may be assumed to have (manylinux_2_28: Debian 10, Ubuntu 18.10, RHEL 8,
# Jetson's Ubuntu 20.04, Raspberry Pi OS 11 and newer). pip does not derive the older manylinux
# tags from a --platform, so every tag up to it is given.
GLIBC_MINOR = 28
LEGACY_TAGS = {"manylinux1": 5, "manylinux2010": 12, "manylinux2014": 17}
CA_BUNDLE = "/etc/ssl/certs/ca-certificates.crt"
PUBLIC_INDEX = "https://pypi.org/simple"


def platform_tags(machine: str) -> list[str]:
    """Every manylinux tag a Linux `machine` with glibc 2.GLIBC_MINOR installs."""
    tags = [f"manylinux_2_{minor}_{machine}" for minor in range(GLIBC_MINOR, 4, -1)]
    legacy = [f"{name}_{machine}" for name, minor in LEGACY_TAGS.items() if minor <= GLIBC_MINOR]
    return tags + legacy


def target_environment(python: str, machine: str) -> dict[str, str]:
    """The marker variables of CPython `python` on Linux `machine`."""
    return {
        "python_version": python,
        "python_full_version": f"{python}.0",
        "sys_platform": "linux",
        "platform_system": "Linux",
        "platform_machine": machine,
        "os_name": "posix",
        "implementation_name": "cpython",
        "platform_python_implementation": "CPython",
    }


def requirements_for(lock: Path, env: dict[str, str]) -> list[str]:
    """The lock's entries (with their hashes) whose marker holds in `env`, without the marker."""
    entries: list[str] = []
    for block in lock.read_text().replace("\\\n", " ").splitlines():
        line = block.split("#", 1)[0].strip()
        if not line:
            continue
        spec, *hashes = line.split(" --hash=")
        requirement = Requirement(spec.strip())
        if requirement.marker is not None and not requirement.marker.evaluate(env):
            continue
        requirement.marker = None
        entries.append(" ".join([str(requirement), *(f"--hash={h}" for h in hashes)]))
    return entries


def check(lock: Path, python: str, machine: str, dest: Path) -> tuple[bool, str]:
    """pip download every file the lock pins for this target; (ok, the last line of pip's say)."""
    entries = requirements_for(lock, target_environment(python, machine))
    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as handle:
        handle.write("\n".join(entries) + "\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "UV_"))}
    env["PIP_CONFIG_FILE"] = os.devnull
    command = [
        sys.executable, "-m", "pip", "download", "--isolated", "--disable-pip-version-check",
        "--index-url", PUBLIC_INDEX, "--only-binary=:all:", "--no-deps", "--require-hashes",
        "--python-version", python, "--implementation", "cp", "-d", str(dest), "-r", handle.name,
    ]  # fmt: skip
    for tag in platform_tags(machine):
        command += ["--platform", tag]
    if Path(CA_BUNDLE).is_file():
        command[4:4] = ["--cert", CA_BUNDLE]
    done = subprocess.run(command, capture_output=True, text=True, env=env, check=False)
    os.unlink(handle.name)
    said = (done.stderr.strip() or done.stdout.strip()).splitlines()
    errors = [s for s in said if s.startswith("ERROR")]
    last = errors[-1] if errors else f"{len(entries)} files"
    return done.returncode == 0, last


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--lock", action="append", help="lock file(s); default: all three")
    parser.add_argument("--python", action="append", help="Python version(s); default 3.10-3.13")
    parser.add_argument("--arch", action="append", choices=ARCHES)
    args = parser.parse_args()
    results: list[tuple[str, str, str, bool, str]] = []
    with tempfile.TemporaryDirectory(prefix="lock-check-") as tmp:
        for lock_name in args.lock or LOCKS:
            for machine in args.arch or ARCHES:
                for python in args.python or PYTHONS:
                    dest = Path(tmp) / f"{Path(lock_name).stem}-{machine}-{python}"
                    ok, said = check(ROOT / lock_name, python, machine, dest)
                    known = NOT_SERVED.get((lock_name, machine))
                    if not ok and known:
                        print(f"n/a  {lock_name} linux/{machine} cp{python}: {known}", flush=True)
                        continue
                    results.append((lock_name, machine, python, ok, said))
                    verdict = "ok  " if ok else "FAIL"
                    print(f"{verdict} {lock_name} linux/{machine} cp{python}: {said}", flush=True)
    failed = [r for r in results if not r[3]]
    print(f"\n{len(results) - len(failed)} of {len(results)} combinations install")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
