"""A robot installed as a robot host installs it serves a ROS 2 camera (issue 33).

A robot installs `requirements/runtime.lock`, then the project without resolving anything again
(README, "Set up and run"). That lock has no scikit-image, no matplotlib and no torch. Regression
guard: a robot whose source is `ros2:` measured its codecs at start on scikit-image's photographs
and stopped with "install elasticfog[data]" on exactly the install a robot has. Its codecs are now
measured on the first frames it serves (`robotd.robot_profile.FirstFramesRefinement`).

The test makes that install in a fresh virtual environment (pip with this host's configuration,
so a local cache or index serves the pinned, hash-checked files), checks that the extras are not
importable there, and runs that environment's `elasticfog`: a registry, a cloud daemon (a cloud
host installs the same lock) and a robot with a `ros2:` source, on loopback. This process plays
the camera, a ROS 2 publisher of `sensor_msgs/msg/Image` over rmw_zenoh made with the project's own
node (`robotd.ros2_node`; its frames are views of a photograph, from the test's environment), and
reads the results on the robot's out key. What must hold: frames are served and each result
carries its frame's header stamp, the codecs are measured on the robot's first frames, frames go
on being served afterwards, and the robot logs no traceback. The robot's resident set is
reported (docs/ros2.md, "Figures").

Skipped only when pip reports that no package index could be reached (its connection errors);
any other failure of the install fails the test. The install (about 40 s with a warm pip cache)
is made before the test's own time bound (`e2e_watchdog`) starts; pip's steps have their own.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest

from common import rmw_zenoh
from common.defaults import DEFAULT_CALIBRATION_FRAMES
from common.photos import photo_bgr
from common.ros2_messages import typestore
from robotd.results.client import Result, RobotClient
from robotd.ros2_node import acquire_node

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.usefixtures("e2e_watchdog")]

REPO = Path(__file__).resolve().parents[2]
RUNTIME_LOCK = REPO / "requirements" / "runtime.lock"
# What a robot host does not install: the `data`, `plots` and `bench` extras' modules.
EXTRAS_MODULES = ("skimage", "matplotlib", "torch")
# Left out of the copy the project is installed from (nothing of them is installed).
NOT_INSTALLED = (".*", "__pycache__", "*.egg-info", "build", "dist", "tests", "docs", "benchmarks")

VENV_TIMEOUT_S = 120.0
PIP_TIMEOUT_S = 900.0
"""The lock's files from the public index, no cache, on a slow link (the README measured the
larger dev lock at about 2 minutes)."""
# What pip prints when an index does not answer (urllib3's connection errors, pip's failed
# fetch): the only failure of the install the test is skipped for.
UNREACHABLE_INDEX = (
    "NewConnectionError",
    "ConnectTimeoutError",
    "Could not fetch URL",
    "Network is unreachable",
    "Temporary failure in name resolution",
    "ProxyError",
)

ROBOT = "robot-1"
# A topic of this test's own: the codec measurement is cached by source, and no other test
# may have measured this one before the robot here starts.
CAMERA = "/runtime_lock/camera/image_raw"
IMAGE = rmw_zenoh.TopicType.of("sensor_msgs/msg/Image")
CAMERA_H, CAMERA_W = 480, 640
FIRST_STAMP_NS = 1_700_000_000_000_000_000
SERVED_AFTER_MEASUREMENT = 5
"""Frames the robot must serve after its codecs are measured (on the policy built on them)."""
FRAME_TIMEOUT_S = 2.0
"""How long a frame's result is awaited before the next frame is published (the first frames
may reach no subscriber while the robot's subscription propagates)."""
WAIT_S = 60.0
MEASURED_LINE = f"codecs measured on the first {DEFAULT_CALIBRATION_FRAMES} frames served"
MIB = 1 << 20


@dataclass(frozen=True)
class RuntimeVenv:
    """A virtual environment with the runtime lock and the project, nothing else."""

    path: Path

    @property
    def python(self) -> Path:
        return self.path / "bin" / "python"

    @property
    def elasticfog(self) -> Path:
        return self.path / "bin" / "elasticfog"


def _run(argv: list[str], timeout_s: float) -> subprocess.CompletedProcess[str]:
    """`argv` with this process's environment (pip's configuration, cache and index with it)."""
    return subprocess.run(
        argv,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env={**os.environ, "PIP_NO_INPUT": "1"},
    )


def _text(data: str | bytes | None) -> str:
    return data.decode(errors="replace") if isinstance(data, bytes) else data or ""


def _pip(venv: RuntimeVenv, *args: str) -> None:
    """`pip install ARGS` in `venv` (one retry per file, so that a connection error is printed):
    a skip when pip reports that no index answered, else a failure with pip's output when the
    install fails or runs past PIP_TIMEOUT_S."""
    argv = [str(venv.python), "-m", "pip", "install", "--retries", "1", *args]
    try:
        done = _run(argv, PIP_TIMEOUT_S)
    except subprocess.TimeoutExpired as exc:
        code, output = f"past {PIP_TIMEOUT_S:.0f} s", _text(exc.stdout) + _text(exc.stderr)
        found_nothing = True  # still retrying its connections
    else:
        if done.returncode == 0:
            return
        code, output = str(done.returncode), done.stdout + done.stderr
        found_nothing = "No matching distribution found" in output
    reasons = [marker for marker in UNREACHABLE_INDEX if marker in output]
    if reasons and found_nothing:
        pytest.skip(f"pip reached no package index ({', '.join(reasons)}): {output[-400:]}")
    pytest.fail(f"pip install {' '.join(args)} failed ({code}):\n{output[-4000:]}")


@pytest.fixture(scope="module")
def runtime_venv(tmp_path_factory: pytest.TempPathFactory) -> RuntimeVenv:
    """`python -m venv`, `pip install --require-hashes -r requirements/runtime.lock`, then
    `pip install --no-deps` of a copy of the project (README; deploy/Dockerfile does the same),
    and `pip check`."""
    root = tmp_path_factory.mktemp("runtime-lock")
    venv = RuntimeVenv(root / "venv")
    made = _run([sys.executable, "-m", "venv", str(venv.path)], VENV_TIMEOUT_S)
    assert made.returncode == 0, made.stderr
    _pip(venv, "--require-hashes", "-r", str(RUNTIME_LOCK))
    source = root / "elasticfog"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(*NOT_INSTALLED))
    _pip(venv, "--no-deps", str(source))
    checked = _run([str(venv.python), "-m", "pip", "check"], VENV_TIMEOUT_S)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    return venv


def camera_frame(n: int) -> np.ndarray:
    """Frame `n` as the camera sends it: RGB, 640×480, a view of a photograph moved by n px."""
    photo = photo_bgr("astronaut")[:, :, ::-1]  # 512×512, RGB
    big = np.pad(photo, ((0, CAMERA_H), (0, CAMERA_W), (0, 0)), mode="reflect")
    return np.ascontiguousarray(big[n : n + CAMERA_H, n : n + CAMERA_W])


def image_cdr(rgb: np.ndarray, stamp_ns: int) -> bytes:
    """`rgb` as a sensor_msgs/msg/Image (rgb8) in CDR, by rosbags' type store."""
    types = typestore().types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    msg = types["sensor_msgs/msg/Image"](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id="camera_optical",
        ),
        height=rgb.shape[0],
        width=rgb.shape[1],
        encoding="rgb8",
        is_bigendian=0,
        step=rgb.shape[1] * 3,
        data=rgb.reshape(-1),
    )
    return bytes(typestore().serialize_cdr(msg, "sensor_msgs/msg/Image"))


def serve_until(
    publish: Callable[[int], int], client: RobotClient, done: Callable[[list[Result]], bool]
) -> list[Result]:
    """Publish frames one at a time (the next once the last one's result came, or after
    FRAME_TIMEOUT_S) until `done(results)`, bounded by WAIT_S."""
    results: list[Result] = []
    deadline = time.monotonic() + WAIT_S
    n = 0
    while not done(results):  # bounded by the deadline
        assert time.monotonic() < deadline, f"{len(results)} results in {WAIT_S} s"
        stamp = publish(n)
        n += 1
        result = next((r for r in client.results(FRAME_TIMEOUT_S) if r.stamp_ns == stamp), None)
        if result is not None:
            results.append(result)
    return results


def test_a_robot_from_the_runtime_lock_serves_a_ros2_camera(
    runtime_venv: RuntimeVenv,
    make_fleet: Any,
    local_fleet: Any,
    record_property: Callable[[str, object], None],
) -> None:
    probe = (
        "import importlib.util as u; "
        f"print(','.join(m for m in {EXTRAS_MODULES!r} if u.find_spec(m) is not None))"
    )
    found = _run([str(runtime_venv.python), "-c", probe], VENV_TIMEOUT_S)
    assert found.returncode == 0 and found.stdout.strip() == "", found.stdout + found.stderr

    fleet = make_fleet(machines={ROBOT: {"source": f"ros2:{CAMERA}"}})
    lf = local_fleet(fleet, argv0=[str(runtime_venv.elasticfog)])
    lf.start_registry()
    lf.start_clouds(["edge-1"])
    sent: dict[int, int] = {}  # stamp -> frame published
    with RobotClient(fleet.config, ROBOT) as client:
        robot = lf.start_robot(ROBOT, wait=True)  # the fleet's policy, elastic: it learns codecs
        node = acquire_node(lf.session, 0, "camera")
        camera = node.publisher(CAMERA, IMAGE, rmw_zenoh.DEFAULT_QOS)

        def publish(n: int) -> int:
            stamp = FIRST_STAMP_NS + n * 33_000_000
            camera.put(image_cdr(camera_frame(n), stamp), stamp)
            sent[stamp] = n
            return stamp

        def measured_and_served(results: list[Result]) -> bool:
            after = [r for r in results if r.frame >= DEFAULT_CALIBRATION_FRAMES]
            return len(after) >= SERVED_AFTER_MEASUREMENT and MEASURED_LINE in robot.log_text()

        try:
            results = serve_until(publish, client, measured_and_served)
        finally:
            camera.close()
            node.release()
        rss = psutil.Process(robot.pid).memory_info().rss
    assert all(r.stamp_ns in sent for r in results), "each result carries its frame's stamp"
    assert all(np.isfinite(a).all() for r in results for a in r.outputs.values())
    robot.check_alive()
    served = {r.served_by.value for r in results}
    record_property("robot_rss_mib", round(rss / MIB))
    print(
        f"\nrobot from the runtime lock: {len(results)} results ({', '.join(sorted(served))}), "
        f"RSS {rss / MIB:.0f} MiB"
    )
