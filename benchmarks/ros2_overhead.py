"""What speaking ROS 2 costs a robot: the in/out path's time per frame and the daemon's memory.

1. Overhead (issue 24, target <= 2 ms median on loopback): a 640×480 `sensor_msgs/msg/Image`
   (rgb8, a real photograph) from the moment a ROS 2 publisher puts it on its rmw_zenoh key to
   the moment a ROS 2 subscriber has the frame's result, minus the model's own time. The parts
   are the runtime's own, on real Zenoh sessions on loopback (a router, the robot's peer session,
   the camera's and the planner's): the `ros2:` source (`robotd.sources.ros2`: take the newest
   message, CDR -> BGR), the model's input made from the frame (`common.image_input`: resize
   to the model's input, layout), and the results sink (`robotd.results.ros2`: outputs ->
   Float32MultiArray, a 32FC1 Image for an H×W output, a Classification for a 1×N one, the
   TensorList of all, the model view's CameraInfo, each with rmw_zenoh's attachment, put) up to
   the subscriber's callback of the last of them (the CameraInfo). The model is not run: its
   outputs (of the model's shapes) are given, so what is measured is the path alone. Frames go
   one at a time (the next once the result came), so no frame waits behind another. Two output
   sets: a classifier's (1×1000) and a dense map (1×1×480×640, as a stereo model's disparity:
   Float32MultiArray, 32FC1 Image and TensorList, 1.2 MB each).
2. Memory: the resident set size of a real `elasticfog robot` subprocess (same model, same
   policy, `--policy robot` so no cloud is needed) once it has served a few frames, fed by the
   `photo` source, and fed by `ros2:` with `results: {ros2: ...}` (this script publishes the
   frames). The difference is what the ROS 2 parts (rosbags' type store, the node, the
   subscriber and publishers) add. `--elasticfog PATH` runs the robots with another
   installation's CLI, e.g. a virtual environment made as a robot host makes it (README:
   `requirements/runtime.lock`, then the project with `--no-deps`); that one has no
   photographs (the `data` extra), so measure it with `--sources ros2`.

    python benchmarks/ros2_overhead.py [--frames 200] [--skip-memory] [--json]
    python benchmarks/ros2_overhead.py --skip-overhead --sources ros2 --elasticfog V/bin/elasticfog

The host may be shared: figures are medians of one run, with the p90 beside them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np
import psutil
import zenoh

from common import rmw_zenoh
from common.config import load_fleet
from common.image_input import ImageInputs
from common.partition.manifest import TensorSpec
from common.ros2_messages import MessageType, typestore
from common.session import init_runtime
from common.source_spec import parse_ros2_source
from deploy.local_fleet import LocalFleet, write_local_fleet
from deploy.procs import free_tcp_port
from robotd.frame_path.frame import FrameResult
from robotd.results.ros2 import CAMERA_INFO_TOPIC, Ros2ResultSink
from robotd.sources.frame_sources import SourceSession
from robotd.sources.ros2 import Ros2Source

HEIGHT, WIDTH = 480, 640
CAMERA = "/camera/image_raw"
PREFIX = "/elasticfog/bench"
WAIT_S = 10.0
MODEL = "zoo:resnet"
MODEL_SHAPE = [3, 224, 224]
MEMORY_FRAMES = 20
RSS_READINGS = 5
RSS_INTERVAL_S = 0.1
STARTUP_TIMEOUT_S = 120.0


def photograph() -> np.ndarray:
    from skimage import data

    return np.ascontiguousarray(cv2.resize(data.astronaut(), (WIDTH, HEIGHT)))


def image_cdr(rgb: np.ndarray, stamp_ns: int) -> bytes:
    types = typestore().types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    msg = types["sensor_msgs/msg/Image"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="cam"
        ),
        height=rgb.shape[0],
        width=rgb.shape[1],
        encoding="rgb8",
        is_bigendian=0,
        step=rgb.shape[1] * 3,
        data=rgb.reshape(-1),
    )
    return bytes(typestore().serialize_cdr(msg, "sensor_msgs/msg/Image"))


def _session(endpoint: str, *, router: bool = False) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"' if router else '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if router:
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    else:
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    return zenoh.open(conf)


def measure_overhead(frames: int, outputs: dict[str, np.ndarray], workdir: Path) -> dict[str, Any]:
    """Per-frame times (ms) of the path, one frame at a time (see the module docstring)."""
    init_runtime()
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config_path = write_local_fleet(workdir / f"o{len(outputs)}", fleet="bench", model=MODEL)
    cfg = load_fleet(config_path)
    inputs = ImageInputs([TensorSpec("input", "float32", [1, *MODEL_SHAPE])])
    rgb = photograph()
    router = _session(endpoint, router=True)
    robot, camera, planner = (_session(endpoint) for _ in range(3))
    done = threading.Event()
    received: dict[str, float] = {}
    info_type = rmw_zenoh.TopicType.of(MessageType.CAMERA_INFO.value, typestore())

    def on_result(sample: zenoh.Sample) -> None:
        received["at"] = time.perf_counter()
        done.set()

    try:
        source = Ros2Source(
            parse_ros2_source(f"ros2:{CAMERA}"),
            SourceSession(robot, cfg, "r"),
            height=MODEL_SHAPE[1],
            width=MODEL_SHAPE[2],
        )
        sink = Ros2ResultSink(cfg, "r", robot, PREFIX, height=MODEL_SHAPE[1], width=MODEL_SHAPE[2])
        # The model view's CameraInfo is the last message a frame's results publish.
        key = rmw_zenoh.topic_key(0, f"{PREFIX}/{CAMERA_INFO_TOPIC}", info_type)
        sub = planner.declare_subscriber(key, on_result)
        image_key = rmw_zenoh.topic_key(0, CAMERA, rmw_zenoh.TopicType.of("sensor_msgs/msg/Image"))
        pub = camera.declare_publisher(image_key)
        payloads = [
            image_cdr(np.roll(rgb, k, axis=1), 1_700_000_000_000_000_000 + k) for k in range(8)
        ]
        totals, decode, feeds, publish = [], [], [], []
        # Warm up until the path is matched end to end (the first puts may precede matching).
        for n in range(-50, frames):  # bounded
            payload = payloads[n % len(payloads)]
            done.clear()
            t0 = time.perf_counter()
            pub.put(payload)
            frame = source.read()
            t1 = time.perf_counter()
            inputs.feeds(frame)
            t2 = time.perf_counter()
            stamp = source.last_stamp_ns or 0
            sink.publish(FrameResult(n, {}, outputs, None, "robot", False, stamp))  # type: ignore[arg-type]
            t3 = time.perf_counter()
            if not done.wait(WAIT_S):
                raise RuntimeError(f"no result for frame {n} within {WAIT_S} s")
            if n >= 0:
                totals.append((received["at"] - t0) * 1e3)
                decode.append((t1 - t0) * 1e3)
                feeds.append((t2 - t1) * 1e3)
                publish.append((t3 - t2) * 1e3)
        sub.undeclare()
        pub.undeclare()
        sink.close()
        source.close()
    finally:
        for s in (planner, camera, robot, router):
            s.close()

    def stats(values: list[float]) -> dict[str, float]:
        q = statistics.quantiles(values, n=10)
        return {"median_ms": statistics.median(values), "p90_ms": q[-1]}

    return {
        "frames": frames,
        "outputs": {k: list(v.shape) for k, v in outputs.items()},
        "total": stats(totals),
        "to_frame": stats(decode),
        "model_input": stats(feeds),
        "results_out": stats(publish),
    }


def _rss(pid: int) -> int:
    process = psutil.Process(pid)
    readings = []
    for _ in range(RSS_READINGS):
        readings.append(process.memory_info().rss)
        time.sleep(RSS_INTERVAL_S)  # readings spread over half a second, not a readiness wait
    return int(statistics.median(readings))


def _feed(session: zenoh.Session, key: str, rgb: np.ndarray, stop: threading.Event) -> None:
    """Publish `rgb` as an Image on `key` at 10 fps until `stop`."""
    while not stop.wait(0.1):  # bounded by stop
        session.put(key, image_cdr(rgb, time.time_ns()))


MEMORY_SOURCES: dict[str, dict[str, Any]] = {
    "photo": {"source": "photo"},
    "ros2": {"source": f"ros2:{CAMERA}", "results": {"ros2": PREFIX}},
}


def measure_memory(
    workdir: Path,
    sources: Sequence[str] = tuple(MEMORY_SOURCES),
    argv0: Sequence[str] | None = None,
) -> dict[str, int]:
    """RSS (bytes) of a robot daemon fed by `photo`, and by `ros2:` publishing its results (those
    of `sources`); `argv0`: the robots' CLI (None: this installation's)."""
    results: dict[str, int] = {}
    rgb = photograph()
    for name in sources:
        machine = MEMORY_SOURCES[name]
        config = write_local_fleet(
            workdir / name,
            fleet=f"mem-{name}",
            model=MODEL,
            changes={"input_shape": MODEL_SHAPE, "machines": {"robot-1": machine}},
        )
        with LocalFleet(
            config, workdir / f"run-{name}", startup_timeout_s=STARTUP_TIMEOUT_S, argv0=argv0
        ) as lf:
            lf.start_registry()
            tap = lf.tap("robot-1")
            robot = lf.start_robot("robot-1", "--policy", "robot", "--fps", "10")
            stop = threading.Event()
            publisher = None
            if name == "ros2":
                key = rmw_zenoh.topic_key(
                    0, CAMERA, rmw_zenoh.TopicType.of("sensor_msgs/msg/Image")
                )

                publisher = threading.Thread(
                    target=_feed, args=(lf.session, key, rgb, stop), daemon=True
                )
                publisher.start()
            tap.wait_frame(MEMORY_FRAMES, timeout_s=STARTUP_TIMEOUT_S, procs=[robot])
            results[name] = _rss(robot.pid)
            stop.set()
            if publisher is not None:
                publisher.join()
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--skip-overhead", action="store_true")
    parser.add_argument(
        "--repeat", type=int, default=3, help="robot daemons per source (median RSS)"
    )
    parser.add_argument(
        "--sources",
        default=",".join(MEMORY_SOURCES),
        help=f"the robots measured, of {', '.join(MEMORY_SOURCES)}",
    )
    parser.add_argument(
        "--elasticfog",
        type=Path,
        help="the robots' elasticfog (default: this installation's), e.g. a runtime-lock venv's",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    sources = [name.strip() for name in args.sources.split(",") if name.strip()]
    unknown = [name for name in sources if name not in MEMORY_SOURCES]
    if unknown or not sources:
        parser.error(f"--sources: expected some of {', '.join(MEMORY_SOURCES)}, got {args.sources}")
    argv0 = None if args.elasticfog is None else [str(args.elasticfog)]
    result: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if not args.skip_overhead:
            result["classifier"] = measure_overhead(
                args.frames, {"logits": np.zeros((1, 1000), np.float32)}, work
            )
            result["dense_map"] = measure_overhead(
                args.frames, {"disparity": np.ones((1, 1, HEIGHT, WIDTH), np.float32)}, work
            )
        if not args.skip_memory:
            runs = [measure_memory(work / f"m{i}", sources, argv0) for i in range(args.repeat)]
            result["rss_runs"] = runs
            result["rss_bytes"] = {k: int(statistics.median(r[k] for r in runs)) for k in sources}
    if args.json:
        print(json.dumps(result))
        return
    for name in ("classifier", "dense_map"):
        if name not in result:
            continue
        r = result[name]
        print(f"{name} {r['outputs']}, {r['frames']} frames at {WIDTH}x{HEIGHT} rgb8:")
        for part in ("total", "to_frame", "model_input", "results_out"):
            print(
                f"  {part:12s} median {r[part]['median_ms']:.2f} ms, p90 {r[part]['p90_ms']:.2f} ms"
            )
    if "rss_bytes" in result:
        rss = result["rss_bytes"]
        shown = ", ".join(f"{k} {v / 2**20:.0f} MiB" for k, v in rss.items())
        if "photo" in rss and "ros2" in rss:
            shown += f" ({(rss['ros2'] - rss['photo']) / 2**20:+.0f} MiB)"
        print(
            f"robot RSS: {shown}; median of {args.repeat} daemons each: "
            f"{[{k: v // 2**20 for k, v in r.items()} for r in result['rss_runs']]} MiB"
        )


if __name__ == "__main__":
    main()
