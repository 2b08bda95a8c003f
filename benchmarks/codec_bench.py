"""Cost of each tensor codec at the crossing: encode and decode time, bytes, fidelity.

Inputs, all real data, no download (scikit-image ships the photograph):
- a photograph (`skimage.data.astronaut`, resized with OpenCV's INTER_AREA) as uint8
  1×240×320×3 and 1×224×224×3, the runtime's camera frames at cut 0;
- a float32 feature map 1×64×60×80: the 240×320 photograph through 64 random zero-mean 3×3×3
  filters at stride 4, then ReLU (about half zeros, spatially correlated like a CNN's early
  activations).

For each codec that applies: median µs of `encode_tensor_as` and of `decode_encoded` (what the
robot and the deployment pay per tensor; msgpack framing excluded), bytes on the wire
(`EncodedTensor.nbytes`), their ratio to raw, and PSNR of the decoded tensor (peak 255 for the
photographs, the map's maximum for the feature map; ∞ = exact). "memcpy" is one copy of the raw
bytes into a preallocated buffer: the floor any codec is compared with.

    python benchmarks/codec_bench.py [--runs 200] [--photo astronaut] [--json]
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import math
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.wire.tensor_codecs import codec_names_for, decode_encoded, encode_tensor_as

WARMUP_RUNS = 10
JPEG_QUALITIES = (50, 80, 95)
FEATURE_CHANNELS = 64
FEATURE_STRIDE = 4
FILTER_SEED = 0
MAX_DECODED_BYTES = 64 * 1024 * 1024


def photo(name: str, height: int, width: int) -> np.ndarray:
    """The photograph as uint8 1×H×W×3 (RGB)."""
    from skimage import data

    rgb = getattr(data, name)()
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)[None]


def feature_map(image: np.ndarray) -> np.ndarray:
    """float32 1×C×(H/4)×(W/4): random zero-mean 3×3 RGB filters at stride 4, then ReLU."""
    rng = np.random.default_rng(FILTER_SEED)
    rgb = image[0].astype(np.float32) / 255.0
    out = []
    for _ in range(FEATURE_CHANNELS):
        kernels = rng.normal(size=(3, 3, 3)).astype(np.float32)
        kernels -= kernels.mean()  # zero-mean: flat regions give 0, edges give ±, ReLU halves
        response = np.zeros(rgb.shape[:2], np.float32)
        for c in range(3):
            response += cv2.filter2D(rgb[..., c], -1, kernels[..., c])
        out.append(response[::FEATURE_STRIDE, ::FEATURE_STRIDE])
    return np.maximum(np.stack(out)[None], 0).astype(np.float32)


def median_us(fn: Callable[[], object], runs: int) -> float:
    for _ in range(WARMUP_RUNS):
        fn()
    samples = []
    clock = time.perf_counter_ns
    gc.disable()  # a collection inside one sample is noise, not the codec's cost
    try:
        for _ in range(runs):
            started = clock()
            fn()
            samples.append(clock() - started)
    finally:
        gc.enable()
    return statistics.median(samples) / 1000


def psnr_db(reference: np.ndarray, decoded: np.ndarray, peak: float) -> float:
    mse = float(np.mean((reference.astype(np.float64) - decoded.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(peak**2 / mse)


def codecs_for(array: np.ndarray) -> list[str]:
    names = []
    for family in codec_names_for(array.dtype, array.shape):
        if family == "jpeg<Q>":
            names += [f"jpeg{q}" for q in JPEG_QUALITIES]
        else:
            names.append(family)
    return names


def measure(label: str, array: np.ndarray, peak: float, runs: int) -> list[dict[str, Any]]:
    rows = []
    buffer = np.empty_like(array)
    rows.append(
        {
            "input": label,
            "codec": "memcpy",
            "bytes": array.nbytes,
            "ratio": 1.0,
            "encode_us": median_us(lambda: np.copyto(buffer, array), runs),
            "decode_us": None,
            "psnr_db": math.inf,
        }
    )
    for name in codecs_for(array):
        enc = encode_tensor_as(array, name)
        decoded = decode_encoded(enc, max_bytes=MAX_DECODED_BYTES)
        rows.append(
            {
                "input": label,
                "codec": name,
                "bytes": enc.nbytes,
                "ratio": enc.nbytes / array.nbytes,
                "encode_us": median_us(functools.partial(encode_tensor_as, array, name), runs),
                "decode_us": median_us(
                    functools.partial(decode_encoded, enc, max_bytes=MAX_DECODED_BYTES), runs
                ),
                "psnr_db": psnr_db(array, decoded, peak),
            }
        )
    return rows


def run(photo_name: str, runs: int) -> list[dict[str, Any]]:
    big = photo(photo_name, 240, 320)
    small = photo(photo_name, 224, 224)
    features = feature_map(big)
    zeros = float(np.mean(features == 0))
    return [
        *measure(f"{photo_name} uint8 1×240×320×3", big, 255.0, runs),
        *measure(f"{photo_name} uint8 1×224×224×3", small, 255.0, runs),
        *measure(
            f"feature map float32 1×64×60×80 ({zeros:.0%} zeros)",
            features,
            float(features.max()),
            runs,
        ),
    ]


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _num(value: float | None, digits: int = 0) -> str:
    if value is None:
        return "—"
    if math.isinf(value):
        return "∞"
    return f"{value:,.{digits}f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200, help="timed runs per codec and input")
    parser.add_argument(
        "--photo", default="astronaut", help="skimage.data photograph (astronaut, chelsea, ...)"
    )
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be >= 1")
    rows = run(args.photo, args.runs)
    if args.json:
        print(json.dumps(rows, indent=2, default=str))
        return
    import simplejpeg
    import zstandard

    print(
        f"Tensor codecs: median of {args.runs} runs on {cpu_name()} ({platform.machine()}), "
        f"Python {platform.python_version()}, numpy {np.__version__}, "
        f"zstandard {zstandard.__version__}, simplejpeg {simplejpeg.__version__}, "
        f"OpenCV {cv2.__version__}\n"
    )
    print("| input | codec | bytes | / raw | encode µs | decode µs | PSNR dB |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['input']} | {r['codec']} | {r['bytes']:,} | {r['ratio']:.3f} "
            f"| {_num(r['encode_us'])} | {_num(r['decode_us'])} | {_num(r['psnr_db'], 1)} |"
        )


if __name__ == "__main__":
    main()
