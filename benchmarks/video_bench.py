"""Video crossings: bytes per frame and encode/decode time of h264 against JPEG 50 and 80, at
equal PSNR, for a still, a slow and a fast camera (the figures of docs/video.md).

Frames, all real data, no download: the robot's `photo` source (`PhotoSource`: a virtual camera
panning over scikit-image's astronaut photograph; speed 0 = still, 0.5 = slow, 2 = fast), at
320×240 and 640×480, as RGB. For each size and camera:

- JPEG at quality Q (50 and 80): each frame coded alone (`encode_tensor_as`), its bytes, encode
  and decode time, and PSNR against the frame;
- h264 (`common.wire.video_codec`: libx264 superfast, zerolatency, no B-frames, one thread) at
  the highest CRF whose mean PSNR over the run is at least that JPEG's ("equal PSNR": at least
  as good a picture), found by bisection over CRF 0..51: the frames coded as one stream (a
  keyframe, then P-frames) and decoded in order; the P-frames' median bytes, the keyframe's
  bytes, median encode and decode ms of a P-frame, and the mean PSNR.

The ratio column is JPEG's median bytes over h264's P-frame median. Times are this host's (one
thread each); a P-frame's time is what a robot's encoder and a deployment's decoder pay per
frame after the first.

    python benchmarks/video_bench.py [--frames 60] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from common.wire.tensor_codecs import decode_encoded, encode_tensor_as
from common.wire.video_codec import MAX_CRF, MIN_CRF, H264Decoder, H264Encoder
from robotd.sources.frame_sources import PhotoSource

SIZES = ((240, 320), (480, 640))
CAMERAS = {"still": 0.0, "slow": 0.5, "fast": 2.0}
JPEG_QUALITIES = (50, 80)
PHOTO = "astronaut"
SEED = 3
MS_PER_S = 1000.0


def frames(height: int, width: int, speed: float, count: int) -> list[np.ndarray]:
    """`count` RGB frames of a camera panning over the photograph at `speed`."""
    source = PhotoSource(height, width, seed=SEED, name=PHOTO, motion="pan", speed=speed)
    return [cv2.cvtColor(source.read(), cv2.COLOR_BGR2RGB) for _ in range(count)]


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255**2 / mse)


def jpeg_row(images: list[np.ndarray], quality: int) -> dict[str, Any]:
    sizes, enc_s, dec_s, psnr = [], [], [], []
    for image in images:
        t0 = time.perf_counter()
        enc = encode_tensor_as(image, f"jpeg{quality}")
        t1 = time.perf_counter()
        got = decode_encoded(enc, max_bytes=image.nbytes)
        t2 = time.perf_counter()
        sizes.append(enc.nbytes)
        enc_s.append(t1 - t0)
        dec_s.append(t2 - t1)
        psnr.append(psnr_db(got, image))
    return {
        "codec": f"jpeg{quality}",
        "bytes": statistics.median(sizes),
        "encode_ms": statistics.median(enc_s) * MS_PER_S,
        "decode_ms": statistics.median(dec_s) * MS_PER_S,
        "psnr_db": statistics.mean(psnr),
    }


def h264_run(images: list[np.ndarray], crf: int) -> dict[str, Any]:
    """The images as one stream at `crf`: P-frame medians, the keyframe, mean PSNR."""
    h, w, _ = images[0].shape
    encoder, decoder = H264Encoder(h, w, 3, crf=crf), H264Decoder(h, w, 3)
    sizes, enc_s, dec_s, psnr = [], [], [], []
    key_bytes = 0
    for i, image in enumerate(images):
        t0 = time.perf_counter()
        data, key = encoder.encode(image, keyframe=False)
        t1 = time.perf_counter()
        got = decoder.decode(data, keyframe=key)
        t2 = time.perf_counter()
        psnr.append(psnr_db(got, image))
        if i == 0:
            key_bytes = len(data)
            continue
        sizes.append(len(data))
        enc_s.append(t1 - t0)
        dec_s.append(t2 - t1)
    return {
        "codec": f"h264 crf{crf}",
        "bytes": statistics.median(sizes),
        "key_bytes": key_bytes,
        "encode_ms": statistics.median(enc_s) * MS_PER_S,
        "decode_ms": statistics.median(dec_s) * MS_PER_S,
        "psnr_db": statistics.mean(psnr),
    }


def h264_at_psnr(images: list[np.ndarray], target_db: float) -> dict[str, Any]:
    """The h264 run at the highest CRF whose mean PSNR is at least `target_db` (PSNR falls as
    CRF rises: bisection)."""
    low, high = MIN_CRF, MAX_CRF  # low always meets the target (CRF 0 is lossless)
    best = h264_run(images, low)
    while low < high:
        mid = (low + high + 1) // 2
        run = h264_run(images, mid)
        if run["psnr_db"] >= target_db:
            low, best = mid, run
        else:
            high = mid - 1
    return best


def measure(count: int) -> list[dict[str, Any]]:
    rows = []
    for height, width in SIZES:
        for camera, speed in CAMERAS.items():
            images = frames(height, width, speed, count)
            for quality in JPEG_QUALITIES:
                jpeg = jpeg_row(images, quality)
                h264 = h264_at_psnr(images, jpeg["psnr_db"])
                base = {"size": f"{width}x{height}", "camera": camera}
                rows.append({**base, **jpeg})
                rows.append({**base, **h264, "vs": jpeg["codec"]})
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| size | camera | codec | bytes/frame | keyframe bytes | JPEG/h264 bytes | "
        "encode ms | decode ms | PSNR dB |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    jpeg_bytes: dict[tuple[str, str, str], float] = {}
    for r in rows:
        if "vs" not in r:
            jpeg_bytes[(r["size"], r["camera"], r["codec"])] = r["bytes"]
            ratio, codec, key = "", r["codec"], ""
        else:
            ratio = f"{jpeg_bytes[(r['size'], r['camera'], r['vs'])] / r['bytes']:.1f}×"
            codec, key = f"{r['codec']} (= {r['vs']})", f"{r['key_bytes']:.0f}"
        lines.append(
            f"| {r['size']} | {r['camera']} | {codec} | {r['bytes']:.0f} | {key} | {ratio} | "
            f"{r['encode_ms']:.2f} | {r['decode_ms']:.2f} | {r['psnr_db']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=60, help="frames per camera (60)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args()
    rows = measure(args.frames)
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    print(f"host: {platform.machine()}, {platform.python_version()}; {args.frames} frames each")
    print(markdown(rows))


if __name__ == "__main__":
    main()
