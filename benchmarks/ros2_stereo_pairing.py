"""How many of a stereo camera's pairs the `ros2:<left>,right=<right>` source serves (issue 33:
at 30 fps with ±5 ms of jitter, >= 99%).

A camera publishes its left and right images (640×480 rgb8, a real photograph) on two ROS 2
topics over rmw_zenoh, from two threads, at `--fps`: image k of each side is stamped at
t0 + k/fps plus its own jitter, uniform in ±`--jitter-ms` (the two sides independent: two
sensors' timestamps), and published at that moment. The robot's source (`robotd.sources
.ros2_stereo`, default slop 10 ms) pairs them on real Zenoh sessions on loopback (a router, the
robot's peer, the camera's), and a frame loop takes each pair as soon as it waits (`read()`,
fitted to a 240×320 model input). Served: pairs the loop took, over pairs published; the source's
own counts (paired, unpaired, dropped as stale: a pair replaced before the loop took it) say where
the others went.

    python benchmarks/ros2_stereo_pairing.py [--seconds 20] [--fps 30] [--jitter-ms 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import zenoh

from benchmarks.ros2_overhead import _session, image_cdr, photograph
from common import rmw_zenoh
from common.config import load_fleet
from common.ros2_messages import MessageType, typestore
from common.session import init_runtime
from common.source_spec import parse_ros2_source
from deploy.local_fleet import write_local_fleet
from deploy.procs import free_tcp_port
from robotd.sources.frame_sources import EndOfStream, SourceSession
from robotd.sources.ros2_stereo import Ros2StereoSource

LEFT, RIGHT = "/stereo/left/image_raw", "/stereo/right/image_raw"
MODEL_HEIGHT, MODEL_WIDTH = 240, 320
MATCH_TIMEOUT_S = 10.0


def _publish_side(
    camera: zenoh.Session,
    key: str,
    image: np.ndarray,
    t0: float,
    fps: float,
    count: int,
    jitter_ms: float,
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    publisher = camera.declare_publisher(key)
    try:
        for k in range(count):
            at = t0 + k / fps + rng.uniform(-jitter_ms, jitter_ms) / 1e3
            wait = at - time.time()
            if wait > 0:
                time.sleep(wait)  # the camera's schedule, not a readiness wait
            publisher.put(image_cdr(image, round(at * 1e9)))
    finally:
        publisher.undeclare()


def measure(seconds: float, fps: float, jitter_ms: float, workdir: Path) -> dict[str, Any]:
    init_runtime()
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    cfg = load_fleet(write_local_fleet(workdir, fleet="pairing", model="zoo:vgg"))
    router = _session(endpoint, router=True)
    robot, camera = _session(endpoint), _session(endpoint)
    image_type = rmw_zenoh.TopicType.of(MessageType.IMAGE.value, typestore())
    keys = {topic: rmw_zenoh.topic_key(0, topic, image_type) for topic in (LEFT, RIGHT)}
    rgb = photograph()
    stop = threading.Event()
    taken = 0
    try:
        source = Ros2StereoSource(
            parse_ros2_source(f"ros2:{LEFT},right={RIGHT}"),
            SourceSession(robot, cfg, "r", stop),
            height=MODEL_HEIGHT,
            width=MODEL_WIDTH,
        )
        # Until both subscriptions are matched, a put may reach nobody: pairs until one comes.
        deadline = time.monotonic() + MATCH_TIMEOUT_S
        while not source.wait_ready(0.05):  # bounded by the deadline
            stamp = time.time_ns()
            camera.put(keys[LEFT], image_cdr(rgb, stamp))
            camera.put(keys[RIGHT], image_cdr(rgb, stamp))
            if time.monotonic() > deadline:
                raise RuntimeError("the stereo source got no pair")
        source.read()
        base = (source.pairing.paired, source.pairing.unpaired, source.dropped_stale)
        count = round(seconds * fps)
        t0 = time.time() + 0.5
        threads = [
            threading.Thread(
                target=_publish_side,
                args=(camera, keys[topic], rgb, t0, fps, count, jitter_ms, seed),
            )
            for seed, topic in enumerate((LEFT, RIGHT))
        ]
        for thread in threads:
            thread.start()

        def loop() -> None:
            nonlocal taken
            try:
                while True:  # bounded: ends at stop
                    source.read()
                    taken += 1
            except EndOfStream:
                pass

        reader = threading.Thread(target=loop)
        reader.start()
        for thread in threads:
            thread.join()
        time.sleep(0.5)  # the last pair's way through the sessions, then the loop stops
        stop.set()
        reader.join()
        source.close()
        paired = source.pairing.paired - base[0]
        return {
            "fps": fps,
            "jitter_ms": jitter_ms,
            "slop_ms": source.spec.slop_ms,
            "published_pairs": count,
            "served": taken,
            "served_share": taken / count,
            "paired": paired,
            "unpaired_images": source.pairing.unpaired - base[1],
            "dropped_stale": source.dropped_stale - base[2],
            "refused": source.refused,
        }
    finally:
        for session in (camera, robot, router):
            session.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--jitter-ms", type=float, default=5.0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(args.seconds, args.fps, args.jitter_ms, Path(tmp))
    if args.json:
        print(json.dumps(result))
        return
    print(
        f"{result['published_pairs']} pairs at {result['fps']:g} fps, ±{result['jitter_ms']:g} ms "
        f"jitter, slop {result['slop_ms']:g} ms: {result['served']} served "
        f"({100 * result['served_share']:.2f}%); paired {result['paired']}, unpaired images "
        f"{result['unpaired_images']}, dropped as stale {result['dropped_stale']}, refused "
        f"{result['refused'] or 'none'}"
    )


if __name__ == "__main__":
    main()
