"""Coverage-guided fuzzing of the wire decoder with atheris (libFuzzer), run by hand.

What it checks: whatever the bytes, each receiver's decode (the cloud on its service, probe and
ctl keys with the InferRequest's tensors decoded too, the robot on replies and routes, the
registry on its request keys and on telemetry, the views CLI) returns a message of a type that
receiver accepts or raises a WireError; and every tensor codec's decode of arbitrary data under
a fuzzer-chosen declaration returns the declared form or raises a WireError. Any other exception
is a finding (libFuzzer saves the input as crash-*); so is an input slower than `-timeout`
seconds (timeout-*) or one that takes the process over `-rss_limit_mb` (oom-*).

atheris is not a dependency of elasticfog and is not in the lock; install it beside the project's
environment, e.g.:

    pip install --target /tmp/atheris atheris      # wheels for CPython 3.8-3.12 on Linux x86-64
    PYTHONPATH=/tmp/atheris .venv/bin/python scripts/fuzz_wire.py -max_total_time=300 \\
        -timeout=10 -rss_limit_mb=2048 /tmp/wire-corpus

Arguments are libFuzzer's. A corpus folder that does not exist yet is created and seeded with
valid messages of every type and encoded tensors of every codec. Replay a finding with
`scripts/fuzz_wire.py crash-<sha1>`. The property tests in tests/unit/test_fuzz_*.py check the
same decoders within a CI budget; this harness is for longer runs.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

try:
    import atheris
except ImportError:
    sys.stderr.write(
        "scripts/fuzz_wire.py needs atheris, which elasticfog does not depend on: install it "
        "with `pip install --target /tmp/atheris atheris` and run this script with "
        "PYTHONPATH=/tmp/atheris (see the docstring).\n"
    )
    sys.exit(2)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

# Coverage feedback from our decoders (msgpack, numpy, zstd and the image libraries are native
# code, which libFuzzer cannot see into from Python).
with atheris.instrument_imports(include=["common"]):
    from common.wire import (
        DTYPES,
        EncodedTensor,
        ErrorReply,
        Message,
        WireError,
        decode,
        decode_encoded,
        decode_tensors,
        encode_tensor_as,
    )
    from common.wire import registry as reg
    from common.wire.cloud_to_robot import INFER_REPLIES, BusyReply, InferReply
    from common.wire.robot_to_cloud import InferRequest
    from common.wire.telemetry import ProbeReport, TelemetryRecord
    from common.wire.tensor_codecs import CODECS

# The limits the receivers use (the cloud's `max_payload_bytes` at 1 MiB to keep runs fast).
CLOUD_LIMIT_BYTES = 1024 * 1024
REGISTRY_LIMIT_BYTES = 64 * 1024
VIEWS_LIMIT_BYTES = 16 * 1024 * 1024
RECEIVERS: list[tuple[tuple[type[Message], ...], int]] = [
    ((InferRequest,), CLOUD_LIMIT_BYTES),
    ((reg.ProbeRequest,), CLOUD_LIMIT_BYTES),
    ((reg.CtlRequest,), CLOUD_LIMIT_BYTES),
    ((reg.DrainReply, ErrorReply), REGISTRY_LIMIT_BYTES),
    (INFER_REPLIES, CLOUD_LIMIT_BYTES),
    ((reg.ProbeReply, ErrorReply), CLOUD_LIMIT_BYTES),
    ((reg.RouteChange,), REGISTRY_LIMIT_BYTES),
    ((reg.RegisterReply,), REGISTRY_LIMIT_BYTES),
    ((reg.RouteChange, ErrorReply), REGISTRY_LIMIT_BYTES),
    ((reg.RegisterRequest,), REGISTRY_LIMIT_BYTES),
    ((reg.RerouteRequest,), REGISTRY_LIMIT_BYTES),
    ((reg.DrainRequest,), REGISTRY_LIMIT_BYTES),
    ((reg.RibQuery,), REGISTRY_LIMIT_BYTES),
    ((TelemetryRecord,), REGISTRY_LIMIT_BYTES),
    ((ProbeReport,), REGISTRY_LIMIT_BYTES),
    ((*reg.RIB_VIEW_REPLIES.values(), ErrorReply), VIEWS_LIMIT_BYTES),
]
CODEC_NAMES = sorted(CODECS)
DTYPE_NAMES = sorted(DTYPES)
# First byte of an input: below this, a wire message for receiver (byte % len(RECEIVERS));
# from it on, an encoded tensor's data for a declaration read from the next bytes.
TENSOR_MODE = 192


def one_input(data: bytes) -> None:
    """libFuzzer's entry point: any exception but a WireError is a finding."""
    if not data:
        return
    if data[0] < TENSOR_MODE:
        accepts, limit = RECEIVERS[data[0] % len(RECEIVERS)]
        try:
            message = decode(data[1:], expect=accepts, max_bytes=limit)
            if isinstance(message, InferRequest):
                decode_tensors(message.tensors, max_bytes=limit)
        except WireError:
            return
        if not isinstance(message, accepts):
            raise AssertionError(f"{type(message).__name__} accepted where {accepts} expected")
        return
    enc = tensor_from(data[1:])
    try:
        array = decode_encoded(enc, max_bytes=CLOUD_LIMIT_BYTES)
    except WireError:
        return
    if array.dtype != DTYPES[enc.dtype] or list(array.shape) != enc.shape:
        raise AssertionError(f"{enc.codec} decoded {array.dtype}{list(array.shape)}, not {enc}")


def tensor_from(data: bytes) -> EncodedTensor:
    """An encoded tensor read from bytes: codec, dtype, rank (0-4) and that many sizes (0-255)
    one byte each; for int8 codecs one float32 scale per channel and a zero point byte; then the
    data."""
    head = data[:3].ljust(3, b"\0")
    codec = CODEC_NAMES[head[0] % len(CODEC_NAMES)]
    dtype = DTYPE_NAMES[head[1] % len(DTYPE_NAMES)]
    rank = head[2] % 5
    shape = list(data[3 : 3 + rank].ljust(rank, b"\1"))
    rest = data[3 + rank :]
    scale = zero_point = None
    if codec.startswith("int8"):
        channels = shape[1] if rank in (3, 4) else 1
        scale = np.frombuffer(rest[: 4 * channels].ljust(4 * channels, b"\1"), "<f4").copy()
        zero = rest[4 * channels] if len(rest) > 4 * channels else 0
        zero_point = np.full(channels, zero, np.float32)
        rest = rest[4 * channels + 1 :]
    return EncodedTensor(
        codec=codec, dtype=dtype, shape=shape, data=rest, scale=scale, zero_point=zero_point
    )


def seeds() -> list[bytes]:
    """Valid inputs to start from: a message of every type for each receiver that takes it, and
    a tensor of every codec family."""
    image = (np.arange(8 * 8 * 3) % 251).astype(np.uint8).reshape(8, 8, 3)
    features = np.linspace(-2, 2, 2 * 3 * 4 * 4, dtype=np.float32).reshape(2, 3, 4, 4)
    request = InferRequest(
        robot="robot-1",
        frame=1,
        model_digest="9f" * 32,
        cut=2,
        tensors={"x": encode_tensor_as(features, "int8+zstd"), "i": encode_tensor_as(image, "png")},
        deadline_s=0.25,
        sent_at=1.0,
    )
    route = reg.RouteChange(robot="robot-1", deployment="edge-1", epoch=3, reason="start", at=1.5)
    messages: list[Message] = [
        request,
        InferReply(
            frame=1,
            deployment="edge-1",
            epoch=3,
            outputs={"y": features},
            queue_s=0.0,
            compute_s=0.01,
        ),
        BusyReply(frame=1, deployment="edge-1", queued=4, capacity=4),
        ErrorReply(code="bad_value", reason="seed"),
        reg.ProbeRequest(sender="robot-1", sent_at=1.0, echo_bytes=16, padding=b"\0" * 16),
        reg.CtlRequest(op=reg.CtlOp.SERVICE, robot="robot-1", epoch=4, sender="registry"),
        reg.RegisterRequest(
            role="robot",
            id="robot-1",
            protocol_version=reg.PROTOCOL_VERSION,
            capabilities=("local_fallback",),
            service="vision",
        ),
        reg.RegisterReply(accepted=True, reason="", protocol_version=1, route=route),
        route,
        reg.RerouteRequest(robot="robot-1", deployment="edge-1", epoch=3, reason="timeouts"),
        reg.DrainRequest(deployment="edge-1"),
        reg.DrainReply(ok=True, moved=("robot-1",)),
        reg.RibQuery(robot="robot-1", limit=5),
        reg.RoutesView(
            rows=(reg.RouteRow(robot="robot-1", deployment="edge-1", epoch=3, since=1.0),),
            generated_at=2.0,
        ),
        TelemetryRecord(
            robot="robot-1",
            frame=1,
            action="cut:2:int8+zstd",
            bytes_up=10,
            bytes_down=4,
            prefix_s=0.01,
            transfer_s=0.01,
            cloud_s=0.01,
            suffix_local_s=0.0,
            latency_s=0.03,
            robot_cpu_s=0.01,
            energy_j=0.1,
            deployment="edge-1",
            fallback=False,
            reason=None,
        ),
        ProbeReport(robot="robot-1", deployment="edge-2", ok=True, at=1.0, rtt_s=0.002),
    ]
    out = []
    for message in messages:
        wire = message.to_wire()
        out += [
            bytes([i]) + wire
            for i, (accepts, _) in enumerate(RECEIVERS)
            if isinstance(message, accepts)
        ]
    tensors: list[tuple[np.ndarray, str]] = [
        (features, "raw"),
        (features, "fp16"),
        (features, "int8"),
        (features, "int8+zstd"),
        (features, "raw+zstd"),
        (image, "jpeg80"),
        (image, "png"),
    ]
    for array, codec in tensors:
        enc = encode_tensor_as(array, codec)
        head = [CODEC_NAMES.index(codec), DTYPE_NAMES.index(array.dtype.name), array.ndim]
        params = b""
        if enc.scale is not None and enc.zero_point is not None:
            params = enc.scale.astype("<f4").tobytes() + bytes([int(enc.zero_point[0])])
        out.append(bytes([TENSOR_MODE, *head, *array.shape]) + params + bytes(enc.data))
    return out


def seed_new_corpora(args: list[str]) -> None:
    """Create each corpus folder named in `args` that does not exist yet, with the seeds."""
    for arg in args[1:]:
        folder = Path(arg)
        if arg.startswith("-") or folder.exists():
            continue
        folder.mkdir(parents=True)
        for seed in seeds():
            (folder / hashlib.sha1(seed).hexdigest()).write_bytes(seed)


def main() -> None:
    seed_new_corpora(sys.argv)
    atheris.Setup(sys.argv, one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
