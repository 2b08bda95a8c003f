"""What the GPU benchmark needs on a machine without network, in parts that travel one per call.

The GPU machine (see benchmarks/gpu_device_run.sh) has no network and takes at most 64 MiB of
files per call, working tree included, while the onnxruntime-gpu wheel alone is about 256 MB
(its CUDA provider library is most of it). Its image already holds Python 3.12, PyTorch with the
CUDA 13 and cuDNN 9 libraries that onnxruntime-gpu loads, numpy, onnx, OpenCV and scikit-image;
what the benchmark lacks is onnxruntime-gpu itself and a few pure-Python or small packages.

`pack` (here, with PyPI): downloads those wheels for CPython 3.12 on manylinux x86_64 at the
versions of the gpu lock (requirements/gpu.lock; until it exists, the dev lock's, and the newest
onnxruntime-gpu), unpacks onnxruntime-gpu's wheel into one xz-compressed tar (about 204 MB, from
256), splits that into parts of `--part-mib` and writes them with the small wheels into
`.gpu-wheels/part-N/` (git ignores the folder), each with the same MANIFEST.json (every file's
size and sha256). It prints the calls to make.

`unpack` (there): collects the parts carried so far into a staging folder outside the checkout
(`stage` does only that, for the calls that carry one part each), checks every file of the
manifest (naming the parts still missing), extracts onnxruntime-gpu and installs the small wheels
into one folder (`--target`), to be put first on PYTHONPATH over the image's own packages.

    python3 benchmarks/gpu_wheels.py pack [--part-mib 54]
    python3 benchmarks/gpu_wheels.py stage [--stage /tmp/ef-gpu/parts]
    python3 benchmarks/gpu_wheels.py unpack --target /tmp/ef-gpu/site [--stage ...]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import lzma
import re
import shutil
import subprocess
import sys
import tarfile
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / ".gpu-wheels"
GPU_LOCK = ROOT / "requirements" / "gpu.lock"
DEV_LOCK = ROOT / "requirements" / "dev.lock"
DEFAULT_STAGE = Path("/tmp/ef-gpu/parts")
MANIFEST = "MANIFEST.json"
ORT_GPU = "onnxruntime-gpu"
ORT_TREE = "onnxruntime-gpu.tar.xz"
PART_MIB = 54
"""A part and the working tree (about 6 MB) stay under a call's 64 MiB."""
MIB = 1024 * 1024
READ_BYTES = 4 * MIB
# What the benchmark imports that the GPU image lacks (its package list: the device docs).
# The daemons would also need eclipse-zenoh, simplejpeg and cryptography; the benchmark runs none.
SMALL = (
    "pydantic",
    "pydantic-core",
    "annotated-types",
    "typing-inspection",
    "platformdirs",
    "zstandard",
)
PYTHON_VERSION = "3.12"
PLATFORMS = (
    "manylinux_2_28_x86_64",
    "manylinux_2_27_x86_64",
    "manylinux_2_17_x86_64",
    "manylinux2014_x86_64",
)


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(READ_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


# -- pack (here) ---------------------------------------------------------------------------------
def pins() -> list[str]:
    """NAME==VERSION of onnxruntime-gpu and the small packages, from the gpu lock (else the dev
    lock; onnxruntime-gpu then unpinned: the newest)."""
    text = GPU_LOCK.read_text() if GPU_LOCK.exists() else ""
    text += "\n" + DEV_LOCK.read_text()
    found = []
    for name in (ORT_GPU, *SMALL):
        match = re.search(rf"^({re.escape(name)}==\S+)", text, re.MULTILINE | re.IGNORECASE)
        found.append(match.group(1) if match else name)
    if not GPU_LOCK.exists():
        log(
            f"{GPU_LOCK.relative_to(ROOT)} does not exist yet: the dev lock's versions, and "
            f"the newest {ORT_GPU}"
        )
    return found


def download(folder: Path) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    platforms = [arg for p in PLATFORMS for arg in ("--platform", p)]
    command = [
        sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
        "--python-version", PYTHON_VERSION, "--implementation", "cp", *platforms,
        "-d", str(folder), *pins(),
    ]  # fmt: skip
    log("$ " + " ".join(command))
    subprocess.run(command, check=True)
    return sorted(folder.glob("*.whl"))


def compress_tree(wheel: Path, out: Path) -> None:
    """The wheel's files as one tar, xz-compressed (with the xz tool, all cores, if there)."""
    raw = out.with_suffix("")
    with zipfile.ZipFile(wheel) as zf, tarfile.open(raw, "w") as tar:
        for info in zf.infolist():
            if info.is_dir():
                continue
            data = zf.read(info)
            entry = tarfile.TarInfo(info.filename)
            entry.size = len(data)
            entry.mode = (info.external_attr >> 16) & 0o777 or 0o644
            entry.mtime = int(time.mktime((*info.date_time, 0, 0, -1)))
            tar.addfile(entry, io.BytesIO(data))
    tool = shutil.which("xz")
    if tool is not None:
        subprocess.run([tool, "-T0", "-6", "-f", str(raw)], check=True)  # writes raw + ".xz"
        return
    with raw.open("rb") as src, lzma.open(out, "wb", preset=6) as dst:
        shutil.copyfileobj(src, dst, READ_BYTES)
    raw.unlink()


def split(path: Path, part_bytes: int) -> list[Path]:
    pieces = []
    with path.open("rb") as f:
        for n in range(10_000):
            data = f.read(part_bytes)
            if not data:
                break
            piece = path.with_name(f"{path.name}.{n:03d}")
            piece.write_bytes(data)
            pieces.append(piece)
    path.unlink()
    return pieces


def pack(part_mib: int) -> None:
    shutil.rmtree(DEST, ignore_errors=True)
    work = DEST / "work"
    wheels = download(work / "download")
    ort = [w for w in wheels if w.name.startswith("onnxruntime_gpu-")]
    if len(ort) != 1:
        raise SystemExit(f"expected one onnxruntime_gpu wheel, found {[w.name for w in ort]}")
    small = [w for w in wheels if w not in ort]
    log(f"compressing {ort[0].name} ({ort[0].stat().st_size / MIB:.0f} MiB)")
    tree = work / ORT_TREE
    compress_tree(ort[0], tree)
    part_bytes = part_mib * MIB
    pieces = split(tree, part_bytes)
    # Parts: the tree's pieces one each; the small wheels where they fit, else a part of their own.
    parts: list[list[Path]] = [[p] for p in pieces]
    for wheel in small:
        size = wheel.stat().st_size
        room = [g for g in parts if sum(f.stat().st_size for f in g) + size <= part_bytes]
        if not room:
            parts.append([])
            room = [parts[-1]]
        room[-1].append(wheel)
    manifest = {
        "onnxruntime_gpu_wheel": ort[0].name,
        "tree": [p.name for p in pieces],
        "wheels": [w.name for w in small],
        "parts": {
            f"part-{i}": {f.name: {"bytes": f.stat().st_size, "sha256": sha256(f)} for f in group}
            for i, group in enumerate(parts, 1)
        },
    }
    for i, group in enumerate(parts, 1):
        folder = DEST / f"part-{i}"
        folder.mkdir()
        for f in group:
            shutil.move(str(f), folder / f.name)
        (folder / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    shutil.rmtree(work)
    sizes = [sum(f.stat().st_size for f in (DEST / name).iterdir()) for name in manifest["parts"]]
    log(
        f"{len(sizes)} parts, {sum(sizes) / MIB:.0f} MiB in all: "
        + ", ".join(f"{s / MIB:.0f}" for s in sizes)
    )
    last = len(sizes)
    for i in range(1, last):
        print(f"call {i}: carry [.gpu-wheels/part-{i}]  bash benchmarks/gpu_device_run.sh stage")
    print(f"call {last}: carry [.gpu-wheels/part-{last}]  bash benchmarks/gpu_device_run.sh run")


# -- stage and unpack (there) --------------------------------------------------------------------
def stage(stage_dir: Path) -> dict[str, Any]:
    """Copy the parts this call carried into `stage_dir`; the manifest."""
    stage_dir.mkdir(parents=True, exist_ok=True)
    for folder in sorted(DEST.glob("part-*")):
        target = stage_dir / folder.name
        target.mkdir(exist_ok=True)
        for f in folder.iterdir():
            if not (target / f.name).exists():
                shutil.copy2(f, target / f.name)
    manifests = sorted(stage_dir.glob(f"part-*/{MANIFEST}"))
    if not manifests:
        raise SystemExit(f"no part carried yet: carry .gpu-wheels/part-N (python3 {__file__} pack)")
    manifest: dict[str, Any] = json.loads(manifests[0].read_text())
    staged = sorted(p.name for p in stage_dir.glob("part-*"))
    log(f"staged: {', '.join(staged)} of {', '.join(manifest['parts'])}")
    return manifest


def check(manifest: dict[str, Any], stage_dir: Path) -> None:
    missing, bad = [], []
    for part, files in manifest["parts"].items():
        for name, meta in files.items():
            path = stage_dir / part / name
            if not path.exists():
                missing.append(part)
            elif path.stat().st_size != meta["bytes"] or sha256(path) != meta["sha256"]:
                bad.append(f"{part}/{name}")
    if missing or bad:
        raise SystemExit(
            f"parts missing: {', '.join(sorted(set(missing))) or 'none'}; damaged: "
            f"{', '.join(bad) or 'none'} (carry each .gpu-wheels/part-N in a call of its own)"
        )


class _Joined(io.RawIOBase):
    """The tree's pieces read as one stream."""

    def __init__(self, paths: list[Path]) -> None:
        self._files: Iterator[Path] = iter(paths)
        self._current: IO[bytes] | None = None
        self._next()

    def _next(self) -> None:
        if self._current is not None:
            self._current.close()
        path = next(self._files, None)
        self._current = None if path is None else path.open("rb")

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        while self._current is not None:
            n = self._current.readinto(buffer)
            if n:
                return n
            self._next()
        return 0


def unpack(stage_dir: Path, target: Path) -> None:
    manifest = stage(stage_dir)
    check(manifest, stage_dir)
    where = {
        name: stage_dir / part / name for part, files in manifest["parts"].items() for name in files
    }
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    pieces = [where[name] for name in manifest["tree"]]
    with (
        io.BufferedReader(_Joined(pieces), READ_BYTES) as stream,
        tarfile.open(fileobj=stream, mode="r|xz") as tar,
    ):
        tar.extractall(target, filter="data")
    wheels = [str(where[name]) for name in manifest["wheels"]]
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile",
         "--target", str(target), *wheels],
        check=True,
    )  # fmt: skip
    log(f"installed {manifest['onnxruntime_gpu_wheel']} and {len(wheels)} wheels into {target}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="here: download, compress and split into .gpu-wheels/part-N")
    p.add_argument("--part-mib", type=int, default=PART_MIB)
    for name in ("stage", "unpack"):
        s = sub.add_parser(name)
        s.add_argument("--stage", type=Path, default=DEFAULT_STAGE)
        if name == "unpack":
            s.add_argument("--target", type=Path, required=True)
    args = parser.parse_args()
    if args.command == "pack":
        pack(args.part_mib)
    elif args.command == "stage":
        stage(args.stage)
    else:
        unpack(args.stage, args.target)


if __name__ == "__main__":
    main()
