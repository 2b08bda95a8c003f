"""fleet.yaml: the fleet's configuration as pydantic models, and its loader.

One file describes a fleet (modeled on FogROS2-LS): its name (used in every key, `ef/<fleet>/...`),
the service and model, where the registry is, the machines (cloud deployments and robots, each with
its own overrides), the initial policy (which deployment serves which robot at start), the latency
bound, the deadline, the split policy, the objective and Zenoh settings.

Every field has a description; unknown keys are refused (a typo must not be silently ignored) and
types are strict (`"10"` is not a number). `load_fleet` turns every problem into one `UserError`
line naming the file and the field path, e.g.
`fleet.yaml: latency_bound.stat: Input should be 'median', 'mean', 'p95', 'max' or 'stddev'`.
Relative paths in the file (model, registry db, TLS files, video sources) are relative to the file.
Reading the YAML and wording the errors is `common.yaml_files`.
"""

from __future__ import annotations

import enum
import functools
import math
import re
import typing
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from common import rmw_zenoh
from common.defaults import (
    DEFAULT_CALIBRATION_FRAMES,
    DEFAULT_MAX_BAD_PIXEL_SHARE,
    DEFAULT_MAX_OUTPUT_REL_ERR,
    DEFAULT_MAX_REQUEST_BYTES,
    DEFAULT_REGISTRY_PORT,
    DEFAULT_STEREO_BASELINE_M,
    DEFAULT_STEREO_HEIGHT_M,
    DEFAULT_STEREO_HFOV_DEG,
    ZOO_PREFIX,
)
from common.errors import UserError
from common.keys import DEFAULT_FLEET, MACHINE_ROLES, Role, validate_id
from common.providers import (
    CPU_PROVIDER,
    ProviderFallback,
    ProviderSpec,
    check_list,
    parse_provider,
)
from common.source_spec import Ros2Spec, SourceError, SourceSpec, parse_source
from common.wire.codec import DEFAULT_MAX_PAYLOAD_BYTES
from common.wire.registry import DeploymentState
from common.yaml_files import format_validation_error, read_yaml

DEFAULT_REGISTRY_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_REGISTRY_PORT}"
DEFAULT_LEASE_MS = 1000
CLI_IDENTITY = "cli"
"""The views CLI's identity: the common name of its read-only certificate (`elasticfog certs`)."""
MIN_REQUEST_BYTES = 1024
"""Below this a registration or a telemetry record (a few hundred bytes) would not fit."""
MAX_REQUEST_BYTES_LIMIT = 16 * 1024 * 1024
"""The registry's requests are small: a limit beyond this protects nothing."""

LatencyStat = Literal["median", "mean", "p95", "max", "stddev"]
LATENCY_STATS: tuple[str, ...] = typing.get_args(LatencyStat)
ROBOT_STATE = "robot"
"""initial_policy's word for a robot (a robot has no deployment state)."""
INITIAL_CLOUD_STATES = (DeploymentState.SERVICE, DeploymentState.STANDBY)
"""A cloud's states at start, in the wire's words (draining is no state to start in)."""
INITIAL_STATES = (ROBOT_STATE, *(s.value for s in INITIAL_CLOUD_STATES))


def _yaml_toggle(value: Any) -> Any:
    # YAML 1.1 reads a bare on/off as true/false: take them as the words that were written.
    if isinstance(value, bool):
        return "on" if value else "off"
    return value


Toggle = Annotated[Literal["auto", "on", "off"], BeforeValidator(_yaml_toggle)]

# Zenoh endpoints: <protocol>/<address>[?metadata][#config]; IP protocols need host:port.
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "vsock", "serial")
_HOST_PORT = re.compile(r"^(\[[0-9a-fA-F:.]+\]|[^\s:/\[\]]+):(\d{1,5})$")


def _check_id(value: str) -> str:
    return validate_id(value, "id")


def _check_endpoint(value: str) -> str:
    protocol, sep, address = value.partition("/")
    address = re.split(r"[?#]", address, maxsplit=1)[0]
    if not sep or protocol not in _IP_PROTOCOLS + _OTHER_PROTOCOLS or not address:
        raise ValueError(
            f"{value!r} is not a Zenoh endpoint; expected <protocol>/<address>, e.g. "
            f"tcp/127.0.0.1:{DEFAULT_REGISTRY_PORT} (protocols: "
            f"{', '.join(_IP_PROTOCOLS + _OTHER_PROTOCOLS)})"
        )
    if protocol in _IP_PROTOCOLS:
        match = _HOST_PORT.match(address)
        if match is None or int(match.group(2)) > 65535:
            raise ValueError(f"{value!r}: expected {protocol}/HOST:PORT with PORT in 0..65535")
    return value


Id = Annotated[str, AfterValidator(_check_id)]
Endpoint = Annotated[str, AfterValidator(_check_endpoint)]
# A provider entry (`cuda`, `{tensorrt: {device_id: 0}}`, `CUDAExecutionProvider` ...), parsed
# into a typed value as the file is read (`common.providers`).
Provider = Annotated[
    ProviderSpec,
    PlainValidator(parse_provider, json_schema_input_type=str | dict[str, Any]),
    PlainSerializer(lambda spec: spec.to_config()),
]


class _Model(BaseModel):
    """Local files: unknown keys and loose types are errors."""

    model_config = ConfigDict(
        extra="forbid", strict=True, validate_default=True, allow_inf_nan=False
    )


class CutsConfig(_Model):
    """Which cuts of the model the runtime may use."""

    max_cut_tensors: int = Field(
        default=2,
        ge=1,
        description="Largest number of tensors a candidate cut may carry (DAG cuts).",
    )
    names: list[str] | None = Field(
        default=None,
        min_length=1,
        description="Restrict candidate cuts to those after these tensors; null: every cut found.",
    )
    segments: bool = Field(
        default=False,
        description="Also build and verify the segment between every two cuts (segment "
        "offload: the cloud runs the part between them; navigation option 3 needs it).",
    )


class DispatchMode(str, enum.Enum):
    """How the deployments serving one robot share its frames (`dispatch.mode`)."""

    ANYCAST = "anycast"
    ROUND_ROBIN = "round_robin"


class DispatchConfig(_Model):
    """How the deployments serving one robot share its frames."""

    mode: DispatchMode = Field(
        default=DispatchMode.ANYCAST,
        strict=False,  # the YAML's string becomes the member
        description="anycast: one deployment serves each robot; round_robin: a pool of "
        "deployments serves it together, each frame computed by exactly one member, in turn "
        "(the robot needs max_in_flight > 1 for the members to overlap).",
    )
    pool_size: int | None = Field(
        default=None,
        ge=1,
        description="round_robin: deployments per pool (the serving one and up to this many "
        "minus one more); null: every live deployment of the service.",
    )

    @model_validator(mode="before")
    @classmethod
    def _shorthand(cls, value: Any) -> Any:
        # `dispatch: round_robin` (the mode alone) is the short form.
        return {"mode": value} if isinstance(value, str) else value

    @model_validator(mode="after")
    def _pool_needs_round_robin(self) -> DispatchConfig:
        if self.pool_size is not None and self.mode is not DispatchMode.ROUND_ROBIN:
            raise ValueError(f"pool_size: only for mode round_robin (mode is {self.mode.value})")
        return self

    def pool_limit(self) -> int:
        """How many deployments may serve one robot (1 in anycast; 0: no limit)."""
        if self.mode is DispatchMode.ANYCAST:
            return 1
        return self.pool_size or 0


class MetricsConfig(_Model):
    """Where a daemon serves its Prometheus metrics (`/metrics`, docs/metrics.md)."""

    port: int | None = Field(
        default=None,
        ge=0,
        le=65535,
        description="TCP port of the daemon's /metrics endpoint; null: not served; 0: any free "
        "port (logged).",
    )
    host: str = Field(
        default="0.0.0.0",
        min_length=1,
        description="Address the /metrics endpoint binds (0.0.0.0: every interface, so a "
        "Prometheus on another host can scrape it).",
    )


class RegistryConfig(_Model):
    """Where the registry is and how it runs."""

    id: Id = Field(default="registry", description="The registry's id (its liveliness token).")
    endpoint: Endpoint = Field(
        default=DEFAULT_REGISTRY_ENDPOINT,
        description="Where every daemon and CLI connects to meet the fleet (the registry's "
        "router).",
    )
    listen: list[Endpoint] = Field(
        default_factory=lambda: [f"tcp/0.0.0.0:{DEFAULT_REGISTRY_PORT}"],
        min_length=1,
        description="Endpoints the embedded Zenoh router listens on.",
    )
    db: str | None = Field(
        default=None,
        description="sqlite file of the routing information base; default: <fleet>.rib.sqlite "
        "next to this file.",
    )
    embedded_router: bool = Field(
        default=True,
        description="Run a Zenoh router inside the registry (false: one runs elsewhere).",
    )
    tls: TlsConfig | None = Field(
        default=None,
        description="The registry's TLS files (cert and key; ca and mtls default to zenoh.tls).",
    )
    metrics: MetricsConfig = Field(
        default_factory=MetricsConfig,
        description="The registry's Prometheus /metrics endpoint (off unless a port is set).",
    )
    max_request_bytes: int = Field(
        default=DEFAULT_MAX_REQUEST_BYTES,
        ge=MIN_REQUEST_BYTES,
        le=MAX_REQUEST_BYTES_LIMIT,
        description="Largest payload the registry reads (register, reroute, drain, RIB queries, "
        "telemetry, probe reports), bytes; a bigger request gets a too_large error reply, a "
        "bigger publication is dropped, both counted.",
    )


class FaultConfig(_Model):
    """Fault injection a cloud daemon starts with (changeable at run time on its ctl key)."""

    delay_ms: float = Field(
        default=0.0, ge=0, description="Extra delay before each reply, milliseconds."
    )
    drop: float = Field(
        default=0.0, ge=0, le=1, description="Probability of not answering a request at all."
    )
    stall: bool = Field(
        default=False, description="Answer nothing while staying alive (a frozen host)."
    )


MAX_BATCH_SIZE = 256
"""Largest batch a cloud daemon forms (a bigger one would only hold memory and latency)."""


class BatchingConfig(_Model):
    """How a cloud daemon shares its workers between robots (`cloudd.batch_queue`): every robot
    has its own queue, served round robin, with at most `max_in_flight_per_robot` requests
    admitted at once (more are answered 'busy'), whether or not batching is on. With `enabled`,
    requests for the same cut from different robots run as one onnxruntime batch."""

    enabled: bool = Field(
        default=False,
        description="Batch requests for the same cut along the batch axis (off: one request "
        "per model run, as before).",
    )
    max_queue_delay_ms: float = Field(
        default=5.0,
        ge=0,
        le=1000,
        description="Longest a request waits for others to join its batch, milliseconds "
        "(never past what its deadline allows).",
    )
    preferred_batch_sizes: list[Annotated[int, Field(ge=1, le=MAX_BATCH_SIZE)]] = Field(
        default_factory=lambda: [8],
        min_length=1,
        description="Batch sizes run without waiting; the largest is the biggest batch.",
    )
    max_in_flight_per_robot: int = Field(
        default=8,
        ge=1,
        description="Cap on the requests of one robot admitted at once (queued or running): a "
        "robot is admitted as many as the frames it keeps in flight (announced at registration, "
        "max_in_flight) plus one, at most this; one that announced nothing gets this. One robot "
        "sending as fast as it can then cannot take every worker or queue slot.",
    )
    heavy_robots_low_priority: bool = Field(
        default=True,
        description="Run the batches of a robot that uses far more of the workers than the "
        "others (1.5x the mean, lately) at the lowest CPU priority (Linux SCHED_IDLE), so "
        "lighter robots' runs take the CPUs first; the heavy robot still gets every idle CPU.",
    )
    buckets: list[Annotated[int, Field(ge=1, le=MAX_BATCH_SIZE)]] | None = Field(
        default=None,
        min_length=1,
        description="With gpu_serving: the batch sizes a run is padded up to (the results of "
        "the padding are dropped), so a suffix only ever sees these shapes; the largest must "
        "be at least the largest preferred size. Null: 1, 2, 4, ... up to the largest "
        "preferred size, and the preferred sizes.",
    )

    @model_validator(mode="after")
    def _sorted_sizes(self) -> BatchingConfig:
        self.preferred_batch_sizes = sorted(set(self.preferred_batch_sizes))
        if self.buckets is not None:
            self.buckets = sorted(set(self.buckets))
            if self.buckets[-1] < self.preferred_batch_sizes[-1]:
                raise ValueError(
                    f"buckets: the largest bucket ({self.buckets[-1]}) is below the largest "
                    f"preferred batch size ({self.preferred_batch_sizes[-1]})"
                )
        return self

    @property
    def bucket_sizes(self) -> tuple[int, ...]:
        """The sizes a batched run is padded up to (`buckets`, or its default), up to the
        first one that holds the largest batch."""
        if self.buckets is not None:
            sizes = set(self.buckets)
        else:
            sizes = {2**i for i in range(self.max_batch.bit_length()) if 2**i <= self.max_batch}
            sizes |= set(self.preferred_batch_sizes)
        ordered = sorted(sizes | {1})
        top = next(b for b in ordered if b >= self.max_batch)
        return tuple(b for b in ordered if b <= top)

    @property
    def max_batch(self) -> int:
        """The largest batch: 1 when batching is off."""
        return max(self.preferred_batch_sizes) if self.enabled else 1


DEFAULT_MAX_TENSOR_BYTES = DEFAULT_MAX_PAYLOAD_BYTES
"""A tensor bigger than this could not travel raw within the default payload limit."""
DEFAULT_MAX_ECHO_BYTES = 64 * 1024
"""Robots ask for 4 KiB of probe echo and the registry for none: more is a probe misused."""
DEFAULT_MAX_VIDEO_STREAMS = 64
"""h264 decoders kept per service plane: ~130 MB at 640x480, more robots than a plane serves."""
DEFAULT_VIDEO_IDLE_S = 30.0
"""An h264 stream unused this long is freed: its robot went elsewhere or stopped."""
DEFAULT_VIDEO_CRF = 24
"""x264's CRF for h264 crossings (`common.wire.video_codec.DEFAULT_CRF`)."""


class CloudLimitsConfig(_Model):
    """What one request may cost a cloud daemon (`cloudd.limits`); over a limit the request gets
    a `too_large` error reply and is counted by reason (`CloudDaemon.refusals`). The in-flight
    limit per robot is `batching.max_in_flight_per_robot`."""

    max_request_bytes: int | None = Field(
        default=None,
        ge=MIN_REQUEST_BYTES,
        description="Largest request payload this deployment reads on its service, probe and "
        "ctl keys, bytes, refused before unpacking; null: the fleet's max_payload_bytes.",
    )
    max_tensor_bytes: int = Field(
        default=DEFAULT_MAX_TENSOR_BYTES,
        ge=1,
        description="Largest decoded size a request's tensor may declare, bytes (dtype size x "
        "elements), refused before anything is decoded.",
    )
    max_echo_bytes: int = Field(
        default=DEFAULT_MAX_ECHO_BYTES,
        ge=1,
        description="Largest echo a probe may ask for, bytes: a probe cannot make this "
        "deployment send back more.",
    )
    max_video_streams: int = Field(
        default=DEFAULT_MAX_VIDEO_STREAMS,
        ge=1,
        description="Robots whose h264 streams each service keeps decoders for at once (about "
        "2 MB each at 640x480); a new robot's keyframe frees the stream idle longest.",
    )
    video_idle_s: float = Field(
        default=DEFAULT_VIDEO_IDLE_S,
        gt=0,
        description="A robot's h264 stream unused this long is freed, s (its next frame is "
        "then refused need_keyframe and resent as a keyframe).",
    )


def _check_ros_topic(value: str | None) -> str | None:
    """A results prefix as a fully qualified ROS 2 topic name (`common.rmw_zenoh.topic_name`)."""
    return None if value is None else rmw_zenoh.topic_name(value)


def _check_result_codec(value: str) -> str:
    from common.wire.errors import WireError
    from common.wire.robot_to_app import result_codec

    try:
        return result_codec(value)
    except WireError as exc:
        raise ValueError(exc.reason) from None


class ResultsConfig(_Model):
    """Robot: how each applied frame's result is published (`ef/<fleet>/out/<robot>`, and on
    ROS 2 topics with `ros2`)."""

    codec: Annotated[str, AfterValidator(_check_result_codec)] = Field(
        default="raw",
        description="Codec of the outputs on ef/<fleet>/out/<robot>: raw (exact), fp16 "
        "(relative error <= 2**-11) or zstd (raw+zstd, exact); lossy codecs are refused.",
    )
    ros2: Annotated[str | None, AfterValidator(_check_ros_topic)] = Field(
        default=None,
        description="ROS 2 topic prefix: each output also published on <prefix>/<output name> "
        "as std_msgs/msg/Float32MultiArray (an H×W or 1×1×H×W output also as a 32FC1 "
        "sensor_msgs/msg/Image on <prefix>/<output name>/image, a 1×N one as a "
        "vision_msgs/msg/Classification on <prefix>/<output name>/classification), all outputs "
        "as an Isaac ROS TensorList on <prefix>/tensors and the model view's CameraInfo on "
        "<prefix>/camera_info, each with the input frame's header, over rmw_zenoh; null: none.",
    )


# Fields that only mean something for one role: setting them on the other is an error.
_CLOUD_ONLY = frozenset({"workers", "queue", "fault", "batching", "limits", "gpu_serving"})
_ROBOT_ONLY = frozenset({"source", "fps", "uplink_mbit", "max_in_flight", "results", "ros2"})


def _check_namespace(value: str) -> str:
    """A node namespace: `/` or a fully qualified ROS 2 name (`common.rmw_zenoh.namespace`)."""
    return rmw_zenoh.namespace(value)


class Ros2Config(_Model):
    """How the fleet's daemons take part in ROS 2 (rmw_zenoh's key space, docs/ros2.md). Set
    fleet-wide (`ros2:`) or per machine (`machines.<id>.ros2:`, whose keys win)."""

    domain_id: int | None = Field(
        default=None,
        ge=0,
        le=rmw_zenoh.MAX_DOMAIN_ID,
        description="ROS 2 domain id of the ros2: sources and results topics; null: the "
        "ROS_DOMAIN_ID environment variable, else 0.",
    )
    endpoint: Endpoint | None = Field(
        default=None,
        description="The ROS 2 graph's Zenoh router (the robot host's rmw_zenohd, e.g. "
        "tcp/127.0.0.1:7447): the robot's ROS 2 traffic (subscriptions, publications, "
        "liveliness tokens) goes through a session of its own connected there, without the "
        "fleet's TLS or access control, and no fleet key reaches it. null: ROS 2 on the fleet's "
        "session (one router for both, on one host).",
    )
    qos_depth: int = Field(
        default=rmw_zenoh.DEFAULT_QOS.depth,
        ge=1,
        le=rmw_zenoh.MAX_QOS_DEPTH,
        description="History depth (keep last N) of the results publishers.",
    )
    namespace: Annotated[str, AfterValidator(_check_namespace)] = Field(
        default=rmw_zenoh.ROOT_NAMESPACE,
        description="Namespace of the robot's ROS 2 node (e.g. /robot1: the node is "
        "/robot1/elasticfog_<robot>); topics are written fully qualified and stay as written.",
    )

    def domain(self) -> int:
        """The domain id in force (the config's, else ROS_DOMAIN_ID's, else 0)."""
        return rmw_zenoh.domain_id(self.domain_id)

    def over(self, base: Ros2Config) -> Ros2Config:
        """These settings over `base`: the keys this section sets win."""
        return base.model_copy(update={k: getattr(self, k) for k in self.model_fields_set})


class MachineConfig(_Model):
    """One machine of the fleet: a cloud deployment or a robot, with its overrides."""

    role: Role = Field(description="'cloud' (serves suffixes) or 'robot' (runs the frame loop).")

    @field_validator("role", mode="before")
    @classmethod
    def _machine_role(cls, value: Any) -> Any:
        if value not in MACHINE_ROLES:
            raise ValueError(f"{value!r} is not a machine role; expected cloud or robot")
        return Role(value)  # the model is strict: the YAML's string becomes the member here

    listen: list[Endpoint] = Field(
        default_factory=list,
        description="Zenoh endpoints this machine listens on; peers reach it there directly, so "
        "they must be reachable from the other machines. Empty: zenoh.listen.",
    )
    connect: list[Endpoint] = Field(
        default_factory=list,
        description="Extra endpoints to connect to, besides the registry endpoint and "
        "zenoh.connect.",
    )
    shared_memory: bool | None = Field(
        default=None, description="Override zenoh.shared_memory for this machine."
    )
    tls: TlsConfig | None = Field(
        default=None,
        description="This machine's TLS files (cert and key; ca and mtls default to zenoh.tls).",
    )
    providers: list[Provider] = Field(
        default_factory=lambda: [ProviderSpec(CPU_PROVIDER)],
        min_length=1,
        description="onnxruntime execution providers, in order of preference: cpu, cuda, "
        "tensorrt or an onnxruntime provider name, each alone or with its options "
        "({cuda: {device_id: 0}}, {tensorrt: {device_id: 0, engine_cache: DIR, "
        "timing_cache: DIR}}).",
    )
    providers_fallback: ProviderFallback = Field(
        default=ProviderFallback.REFUSE,
        strict=False,  # the file's 'allow' is the Enum's value
        description="'refuse': a session that did not get an accelerator it asked for (CUDA, "
        "TensorRT ...) stops the daemon at start, naming the missing provider or library; "
        "'allow': it serves on what it got, with a warning and a flag in its probe reply.",
    )
    gpu_serving: Toggle = Field(
        default="auto",
        description="Cloud: IO binding of the suffix sessions' inputs and outputs, every "
        "batch size the batcher can form warmed up at start, and batched runs padded to "
        "batching.buckets; 'auto': on when the first provider is cuda or tensorrt.",
    )
    threads: int = Field(
        default=0,
        ge=0,
        description="onnxruntime intra-op threads per session; 0: onnxruntime's default.",
    )
    workers: int = Field(
        default=1, ge=1, description="Cloud: inference workers running in parallel."
    )
    queue: int = Field(
        default=4, ge=0, description="Cloud: requests waiting for a worker before answering 'busy'."
    )
    fault: FaultConfig = Field(
        default_factory=FaultConfig, description="Cloud: fault injection at start."
    )
    batching: BatchingConfig = Field(
        default_factory=BatchingConfig,
        description="Cloud: per-robot queues and in-flight limit, and dynamic batching.",
    )
    limits: CloudLimitsConfig = Field(
        default_factory=CloudLimitsConfig,
        description="Cloud: largest request, tensor and probe echo it accepts.",
    )
    source: str = Field(
        default="synthetic",
        description=(
            "Robot: frame source, a spec of common.source_spec: synthetic[:OPTIONS], "
            "photo[:NAME], video:PATH[,loop=false], bag:PATH[:TOPIC] (a rosbag2 recording), "
            "camera:INDEX|/dev/videoINDEX, stereo:world|motorcycle|LEFT,RIGHT[,OPTIONS], zenoh "
            "(frames an application publishes on ef/<fleet>/in/<robot>) or ros2:TOPIC[,OPTIONS] "
            "(a ROS 2 image topic; ros2:LEFT,right=RIGHT[,slop_ms=N]: a stereo camera's two)."
        ),
    )
    fps: float | None = Field(
        default=None,
        gt=0,
        description="Robot: frames per second; null: as fast as frames complete.",
    )
    uplink_mbit: float | None = Field(
        default=None,
        gt=0,
        description="Robot: pace the uplink to this many Mbit/s in the application (emulation).",
    )
    max_in_flight: int = Field(
        default=1,
        ge=1,
        description="Robot: offloaded frames in flight at once (pipelining); 1: each frame's "
        "result is awaited before the next frame starts.",
    )
    results: ResultsConfig = Field(
        default_factory=ResultsConfig,
        description="Robot: how each applied frame's result is published.",
    )
    metrics: MetricsConfig = Field(
        default_factory=MetricsConfig,
        description="This machine's Prometheus /metrics endpoint (off unless a port is set).",
    )
    services: list[Id] | None = Field(
        default=None,
        description="The services this machine serves (a cloud) or uses (a robot), by name; "
        "null: every service of the fleet.",
    )
    ros2: Ros2Config | None = Field(
        default=None,
        description="Robot: its ROS 2 settings over the fleet's ros2 section (e.g. the endpoint "
        "of this robot's own rmw_zenohd); null: the fleet's.",
    )

    @property
    def gpu_serving_on(self) -> bool:
        """`gpu_serving`, resolved: 'auto' is on when the first provider runs on a GPU."""
        if self.gpu_serving == "auto":
            return self.providers[0].gpu
        return self.gpu_serving == "on"

    @model_validator(mode="after")
    def _role_fields(self) -> MachineConfig:
        check_list(self.providers)
        foreign = (_ROBOT_ONLY if self.role is Role.CLOUD else _CLOUD_ONLY) & self.model_fields_set
        if foreign:
            other = Role.ROBOT if self.role is Role.CLOUD else Role.CLOUD
            fields = ", ".join(sorted(foreign))
            raise ValueError(f"{fields}: only for {other} machines (role is {self.role.value!r})")
        try:
            parse_source(self.source)
        except SourceError as exc:
            raise ValueError(f"source: {exc}") from None
        return self


class LatencyBoundConfig(_Model):
    """The latency bound the scheduler keeps (FogROS2-LS): `stat` of the last `window` frames'
    latencies must stay at or below `seconds`."""

    stat: LatencyStat = Field(
        default="median", description="Statistic of the window compared to the bound."
    )
    seconds: float = Field(gt=0, description="The bound, seconds.")
    window: int = Field(default=20, ge=1, description="Frames in the sliding window.")
    hysteresis_s: float = Field(
        default=1.0,
        ge=0,
        description="How long a violation must hold before the robot is moved, seconds.",
    )
    better_margin: float = Field(
        default=0.2,
        ge=0,
        lt=1,
        description="Move a robot that meets its bound only to a deployment predicted better by "
        "this fraction (0.2: 20% lower latency).",
    )

    @model_validator(mode="before")
    @classmethod
    def _fogros_shorthand(cls, data: Any) -> Any:
        # FogROS2-LS writes `latency_bound: {median: 0.3}`; accept it as stat + seconds.
        if isinstance(data, dict) and "stat" not in data and "seconds" not in data:
            stats = [k for k in data if k in LATENCY_STATS]
            if len(stats) == 1:
                stat = stats[0]
                rest = {k: v for k, v in data.items() if k != stat}
                return {**rest, "stat": stat, "seconds": data[stat]}
        return data


POLICY_CHECK_ENTRY_POINT_GROUP = "elasticfog.policies"
"""Where the robot daemon registers its check of a policy name and parameters (`common` never
imports the daemons; loaded when a policy is read, so numpy waits until then)."""


@functools.cache
def _registered_policy_check() -> Callable[..., object] | None:
    for ep in entry_points(group=POLICY_CHECK_ENTRY_POINT_GROUP, name="check"):
        check: Callable[..., object] = ep.load()
        return check
    return None


class PolicyConfig(_Model):
    """The split policy a robot runs."""

    kind: str = Field(
        default="elastic",
        min_length=1,
        description="Policy name, a row of robotd.policies.POLICIES: elastic, ans, "
        "neurosurgeon, robot, cloud[:CODEC], static:K[:CODEC], option:N[:CODEC].",
    )
    params: dict[str, Any] = Field(
        default_factory=dict, description="Policy parameters, checked by the policy's model."
    )

    @model_validator(mode="after")
    def _known_policy(self) -> PolicyConfig:
        check_policy = _registered_policy_check()
        if check_policy is None:  # no robot daemon installed: nothing here runs a policy
            return self
        try:
            check_policy(self.kind, self.params, real_time=True)
        except UserError as exc:
            raise ValueError(str(exc)) from None
        return self


class ObjectiveConfig(_Model):
    """Weights of the cost a policy minimises per frame."""

    latency: float = Field(
        default=1.0, ge=0, description="Weight of end-to-end latency (per second)."
    )
    cpu: float = Field(default=0.0, ge=0, description="Weight of robot CPU time (per CPU second).")
    energy: float = Field(default=0.0, ge=0, description="Weight of robot energy (per joule).")
    bytes: float = Field(
        default=0.0, ge=0, description="Weight of bytes sent and received (per MB)."
    )
    power: dict[str, Any] = Field(
        default_factory=dict, description="Robot power model parameters (watts), free form."
    )


class TlsConfig(_Model):
    """TLS files of `tls/...` endpoints (paths relative to this file): `zenoh.tls` for the whole
    fleet, `machines.<id>.tls`, `registry.tls` and `cli.tls` for one host (unset fields fall back
    to `zenoh.tls`). The certificate's common name is the host's machine id (`elasticfog certs`)."""

    ca: str | None = Field(
        default=None,
        description="The fleet CA's certificate (PEM), which signed every host's (alias: root_ca).",
    )
    cert: str | None = Field(default=None, description="This host's certificate (PEM).")
    key: str | None = Field(default=None, description="This host's private key (PEM).")
    mtls: bool | None = Field(
        default=None,
        description="Mutual TLS: present and require certificates on both ends of every link. "
        "Null: on whenever TLS is on.",
    )

    @model_validator(mode="before")
    @classmethod
    def _root_ca_alias(cls, data: Any) -> Any:
        # Older fleet files name the CA `root_ca` (Zenoh's own word); both mean the same file.
        if isinstance(data, dict) and "root_ca" in data:
            if "ca" in data:
                raise ValueError("give ca or root_ca (the same file), not both")
            data = {("ca" if k == "root_ca" else k): v for k, v in data.items()}
        return data

    @model_validator(mode="after")
    def _pair(self) -> TlsConfig:
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together: give both or neither")
        return self

    @property
    def root_ca(self) -> str | None:
        """The CA file under Zenoh's name for it (`transport/link/tls/root_ca_certificate`)."""
        return self.ca

    @property
    def configured(self) -> bool:
        """Whether any TLS file is set here."""
        return self.ca is not None or self.cert is not None


class CliConfig(_Model):
    """How the views CLI (`elasticfog routes ...`) identifies itself to a TLS fleet."""

    tls: TlsConfig | None = Field(
        default=None,
        description="The read-only `cli` certificate (common name `cli`): it may query the "
        "registry's views and nothing else.",
    )


class ZenohConfig(_Model):
    """Zenoh settings shared by every machine (machines may override listen/connect)."""

    mode: Literal["peer", "client"] = Field(
        default="peer",
        description="peer: talk to other machines directly (the default); client: everything "
        "through the router (e.g. a robot behind NAT).",
    )
    connect: list[Endpoint] = Field(
        default_factory=list, description="Endpoints to connect to besides registry.endpoint."
    )
    listen: list[Endpoint] = Field(
        default_factory=list, description="Default listen endpoints of peers; empty: Zenoh's."
    )
    lease_ms: int = Field(
        default=DEFAULT_LEASE_MS,
        ge=100,
        description="Link lease: a silent peer (frozen host, cut link) is dropped after this, ms.",
    )
    shared_memory: bool = Field(
        default=True,
        description="Shared memory between processes of one host (bypasses the network: turn it "
        "off when shaping traffic between namespaces).",
    )
    tls: TlsConfig = Field(
        default_factory=TlsConfig,
        description="TLS files shared by every host (usually just `ca`; each host's cert and key "
        "go in its own `tls`).",
    )
    access_control: bool | None = Field(
        default=None,
        description="Zenoh access control generated from this file (common/acl.py): each host "
        "may touch only its own keys. Null: on whenever mutual TLS is on (hosts are known by "
        "their certificate's common name).",
    )


def _cloud_state(value: Any) -> DeploymentState | None:
    """The cloud state at start `value` names (service, standby), else None."""
    return next((state for state in INITIAL_CLOUD_STATES if state.value == value), None)


def _initial_entry(value: Any) -> Any:
    """A state for every robot, or a map robot -> service|standby (a cloud serving robots
    differently); a cloud's states become `DeploymentState`s here, where the text enters."""
    if isinstance(value, str):
        if value == ROBOT_STATE:
            return value
        state = _cloud_state(value)
        if state is None:
            raise ValueError(
                f"{value!r} is not a state; expected one of {', '.join(INITIAL_STATES)}"
            )
        return state
    if isinstance(value, dict):
        states: dict[str, DeploymentState] = {}
        for robot, state_text in value.items():
            state = _cloud_state(state_text) if isinstance(robot, str) else None
            if state is None:
                raise ValueError(
                    f"per-robot entry {robot!r}: {state_text!r}; "
                    "expected <robot id>: service|standby"
                )
            states[robot] = state
        return states
    raise ValueError(
        f"expected a state ({', '.join(INITIAL_STATES)}) or a map of robot id to "
        f"service|standby, got {type(value).__name__}"
    )


def _entry_text(entry: Any) -> str:
    """An initial_policy entry as the file wrote it (a state's word, not the enum's repr)."""
    if isinstance(entry, dict):
        entry = {robot: getattr(state, "value", state) for robot, state in entry.items()}
    return repr(getattr(entry, "value", entry))


InitialEntry = Annotated[
    Literal["robot"] | DeploymentState | dict[str, DeploymentState],
    BeforeValidator(_initial_entry),
]


class FidelityConfig(_Model):
    """How close to the uncompressed model a lossy codec at a crossing must keep the answers
    (`common.codec_profile`): the (cut, codec) pairs that meet it are the policy's actions."""

    min_top1_agreement: float = Field(
        default=0.98,
        ge=0,
        le=1,
        description="Least share of calibration frames whose top-1 class (classifier outputs) "
        "a lossy codec must leave unchanged.",
    )
    max_output_rel_err: float | None = Field(
        default=DEFAULT_MAX_OUTPUT_REL_ERR,
        gt=0,
        description="Largest relative L2 error a lossy codec may cause on any output that is "
        "not a classifier's (a classifier's is judged by min_top1_agreement); null: such "
        "outputs admit no lossy codec.",
    )
    max_bad_pixel_share: float | None = Field(
        default=DEFAULT_MAX_BAD_PIXEL_SHARE,
        ge=0,
        le=1,
        description="Largest share of a disparity-like output's pixels a lossy codec may move "
        "by more than 1 px (or make appear or vanish); null: such outputs admit no lossy codec.",
    )
    lossy_features: bool = Field(
        default=False,
        description="Let non-image tensors cross lossy (fp16, int8) where they meet the bound; "
        "by default only images may (JPEG).",
    )
    calibration_frames: int = Field(
        default=DEFAULT_CALIBRATION_FRAMES,
        ge=1,
        le=256,
        description="Frames from the source the codecs are measured on.",
    )
    codecs: list[str] | None = Field(
        default=None,
        min_length=1,
        description="Only these codecs may carry a crossing (raw always may); null: every "
        "codec that applies and meets the bound.",
    )
    video: bool = Field(
        default=False,
        description="Let camera images (cut 0) cross as h264 video too, measured like JPEG "
        "(as a stream of the calibration frames); naming h264 in `codecs` does the same.",
    )


class VideoConfig(_Model):
    """How a robot codes the camera images it sends as video (codec `h264` at cut 0:
    `common.wire.video_codec`); a deployment needs none of it to decode them."""

    crf: int = Field(
        default=DEFAULT_VIDEO_CRF,
        ge=0,
        le=51,
        description="x264's constant rate factor (0 = lossless .. 51 = worst): the quality of "
        "h264 frames, as Q is JPEG's; the default matches JPEG 50's PSNR (docs/video.md).",
    )


# The ranges a stereo camera's geometry (`nav.camera`) is checked against: wide enough for any
# robot's rectified pair, narrow enough to catch a value in the wrong unit (a field of view in
# radians, a baseline in millimetres, a height in centimetres).
STEREO_HFOV_DEG_RANGE = (10.0, 170.0)
MAX_STEREO_BASELINE_M = 2.0
MAX_STEREO_HEIGHT_M = 5.0


class NavCameraConfig(_Model):
    """The stereo camera zoo:stereo is built for (`nav.camera.CameraModel`: a level, rectified
    pair at the model's input size, principal point at the image centre). Every robot and
    deployment builds the same model from it; a ROS 2 stereo source whose CameraInfo says
    otherwise is named in a warning with the lines to put here (docs/ros2.md)."""

    baseline_m: float = Field(
        default=DEFAULT_STEREO_BASELINE_M,
        description="Distance between the two cameras' centres, m (a right CameraInfo's "
        "-P[3]/P[0]); in (0, 2].",
    )
    hfov_deg: float = Field(
        default=DEFAULT_STEREO_HFOV_DEG,
        description="Horizontal field of view of the rectified left image, degrees "
        "(2·atan(width / (2·fx))); in 10..170.",
    )
    height_m: float = Field(
        default=DEFAULT_STEREO_HEIGHT_M,
        description="Height of the camera above the floor, m; in (0, 5].",
    )

    @field_validator("baseline_m")
    @classmethod
    def _baseline(cls, value: float) -> float:
        if not 0 < value <= MAX_STEREO_BASELINE_M:
            raise ValueError(
                f"the stereo baseline must be in (0, {MAX_STEREO_BASELINE_M:g}] m, got {value} "
                "(in metres: 0.06 for 6 cm)"
            )
        return float(value)

    @field_validator("hfov_deg")
    @classmethod
    def _hfov(cls, value: float) -> float:
        low, high = STEREO_HFOV_DEG_RANGE
        if not low <= value <= high:
            raise ValueError(
                f"the horizontal field of view must be in {low:g}..{high:g} degrees, got "
                f"{value} (in degrees, not radians)"
            )
        return float(value)

    @field_validator("height_m")
    @classmethod
    def _height(cls, value: float) -> float:
        if not 0 < value <= MAX_STEREO_HEIGHT_M:
            raise ValueError(
                f"the camera height above the floor must be in (0, {MAX_STEREO_HEIGHT_M:g}] m, "
                f"got {value} (in metres: 0.3 for 30 cm)"
            )
        return float(value)

    def zoo_options(self) -> dict[str, float]:
        """The geometry as zoo build options (`common.zoo.ZooGraph.options`: zoo:stereo's)."""
        return self.model_dump()


class NavConfig(_Model):
    """The navigation app's settings (zoo:stereo)."""

    camera: NavCameraConfig = Field(
        default_factory=NavCameraConfig,
        description="The stereo camera zoo:stereo is built for: baseline_m, hfov_deg, height_m.",
    )


class ServiceConfig(_Model):
    """One service of the fleet: an ONNX model (split like any model) or a Python handler (run
    whole, on the robot or a deployment: its only cut is 0), with the fleet-level keys it
    overrides. What it does not set comes from the fleet."""

    model: str | None = Field(
        default=None,
        min_length=1,
        description="The ONNX model: a path (relative to this file) or zoo:NAME. Exactly one of "
        "model or handler.",
    )
    handler: str | None = Field(
        default=None,
        min_length=1,
        description="A Python function, module:function (the fleet file's folder is searched "
        "first), called with the frame's inputs ({name: uint8 1xHxWx3 RGB}) and params; it "
        "returns {name: numpy array}. Exactly one of model or handler.",
    )
    params: dict[str, Any] = Field(
        default_factory=dict, description="Handler: keyword arguments passed on every call."
    )
    input_shape: list[Annotated[int, Field(ge=1)]] | None = Field(
        default=None,
        min_length=1,
        description="Input shape (a model's dynamic dimensions; a handler's image as C, H, W); "
        "null: the fleet's input_shape (a handler: the source's frame size).",
    )
    cuts: CutsConfig | None = Field(default=None, description="Candidate cuts; null: the fleet's.")
    policy: PolicyConfig | None = Field(
        default=None, description="The split policy; null: the fleet's."
    )
    dispatch: DispatchConfig | None = Field(
        default=None, description="anycast or round_robin; null: the fleet's."
    )
    latency_bound: LatencyBoundConfig | None = Field(
        default=None, description="The latency bound the scheduler keeps; null: the fleet's."
    )
    deadline_s: float | None = Field(
        default=None, gt=0, description="Per-frame deadline, s; null: the fleet's deadline_s."
    )
    objective: ObjectiveConfig | None = Field(
        default=None, description="Per-frame cost weights; null: the fleet's."
    )
    results: ResultsConfig | None = Field(
        default=None, description="How its results are published; null: each robot's results."
    )
    fps: float | None = Field(
        default=None,
        gt=0,
        description="Frames per second this service takes of the robot's capture; null: the "
        "robot's fps (every capture).",
    )
    priority: int = Field(
        default=1,
        ge=0,
        description="Who gives way when a robot's services cannot all be served in time on "
        "its shared uplink and CPU: the lower priority (then the looser deadline) gives way.",
    )

    @model_validator(mode="after")
    def _model_or_handler(self) -> ServiceConfig:
        if (self.model is None) == (self.handler is None):
            raise ValueError("set exactly one of model or handler")
        if self.handler is not None:
            if self.cuts is not None:
                raise ValueError("cuts: a handler has one cut, 0 (the image); remove cuts")
            module, sep, function = self.handler.partition(":")
            if not sep or not module or not function:
                raise ValueError(
                    f"handler: {self.handler!r} is not module:function, e.g. mypkg.tags:detect"
                )
        elif self.params:
            raise ValueError("params: only a handler takes params")
        return self

    @property
    def zoo_model(self) -> str | None:
        """The zoo model name for `model: zoo:NAME`, else None."""
        if self.model is None or not self.model.startswith(ZOO_PREFIX):
            return None
        return self.model[len(ZOO_PREFIX) :]


class FleetConfig(_Model):
    """A fleet: its services (ONNX models or Python handlers), a registry, machines and how
    robots are served. The one-service form (`service` + `model`) is a fleet of one service."""

    fleet: Id = Field(
        default=DEFAULT_FLEET, description="Fleet name, the second chunk of every key."
    )
    service: Id | None = Field(
        default=None,
        description="One-service form: the name of the service robots call (in its anycast "
        "key), with model. Several services: services. Read back, the first service's name.",
    )
    model: str | None = Field(
        default=None,
        min_length=1,
        description="One-service form: the ONNX model, a path (relative to this file) or "
        "zoo:NAME. Read back, the first service's model (null for a handler).",
    )
    services: dict[Id, ServiceConfig] = Field(
        default_factory=dict,
        description="The fleet's services by name (each a model or a handler, with overrides); "
        "the one-service form (service + model) means one service of that name.",
    )
    input_shape: list[Annotated[int, Field(ge=1)]] | None = Field(
        default=None,
        min_length=1,
        description="Input shape, fixing the model's dynamic dimensions.",
    )
    cuts: CutsConfig = Field(default_factory=CutsConfig, description="Candidate cuts.")
    dispatch: DispatchConfig = Field(
        default_factory=DispatchConfig,
        description="anycast (one deployment per robot) or round_robin (a pool per robot).",
    )
    registry: RegistryConfig = Field(default_factory=RegistryConfig, description="The registry.")
    machines: dict[Id, MachineConfig] = Field(
        default_factory=dict, description="Cloud deployments and robots, by id."
    )
    initial_policy: dict[Id, InitialEntry] = Field(
        default_factory=dict,
        description="State of each machine at start (FogROS2-LS): robot, service or standby, or "
        "for a cloud a map robot -> service|standby. Unlisted clouds are standby.",
    )
    latency_bound: LatencyBoundConfig = Field(description="The latency bound the scheduler keeps.")
    deadline_s: float = Field(
        gt=0, description="Per-frame deadline: past it the robot finishes the frame itself, s."
    )
    policy: PolicyConfig = Field(default_factory=PolicyConfig, description="The split policy.")
    objective: ObjectiveConfig = Field(
        default_factory=ObjectiveConfig, description="Per-frame cost weights."
    )
    fidelity: FidelityConfig = Field(
        default_factory=FidelityConfig,
        description="Which lossy codecs may carry a crossing (measured on calibration frames).",
    )
    video: VideoConfig = Field(
        default_factory=VideoConfig,
        description="How camera images crossing as h264 are coded (the robots' encoders).",
    )
    nav: NavConfig = Field(
        default_factory=NavConfig,
        description="The navigation app's settings: the stereo camera zoo:stereo is built for.",
    )
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig, description="Zenoh settings.")
    ros2: Ros2Config = Field(
        default_factory=Ros2Config,
        description="ROS 2 (rmw_zenoh): the domain of ros2: topics, the ROS 2 graph's router, "
        "the results' QoS depth and the node's namespace (a robot's own ros2 section wins).",
    )
    cli: CliConfig = Field(
        default_factory=CliConfig, description="How the views CLI connects (its certificate)."
    )
    max_payload_bytes: int = Field(
        default=DEFAULT_MAX_PAYLOAD_BYTES,
        ge=1024,
        description="Largest message a daemon decodes; bigger ones get an error reply.",
    )

    _source: Path | None = PrivateAttr(default=None)
    # A service's view (`for_service`): the fleet's deployments that do not serve the service.
    _not_serving: frozenset[str] = PrivateAttr(default=frozenset())

    @model_validator(mode="after")
    def _cross_checks(self, info: ValidationInfo) -> FleetConfig:
        self._one_form()
        for name, svc in self.services.items():
            if svc.zoo_model is not None:
                validate_id(svc.zoo_model, f"services.{name}.model: zoo model name")
            if svc.handler is not None:
                from common.handlers import import_handler

                try:
                    import_handler(svc.handler, _base_dir(info))
                except UserError as exc:
                    raise ValueError(f"services.{name}.handler: {exc}") from None
        self._check_machine_services()
        self._check_initial_policy()
        self._check_tls()
        self._check_ros2_sessions()
        self._resolve_paths(_base_dir(info))
        return self

    def _check_tls(self) -> None:
        """Mutual TLS needs a certificate for every host; access control needs mutual TLS."""
        if self.zenoh.access_control and not self.mtls:
            raise ValueError(
                "zenoh.access_control: needs mutual TLS (hosts are known by the common name of "
                "their certificate): set zenoh.tls.ca and each host's tls cert/key"
            )
        if self.zenoh.access_control and self.zenoh.tls.cert is not None:
            raise ValueError(
                "zenoh.access_control: needs a certificate per host (its common name is the "
                "host's id), not one shared zenoh.tls.cert"
            )
        if not self.mtls:
            return
        missing = [f"{where}.tls" for where, tls in self._tls_owners() if tls.cert is None]
        if missing:
            raise ValueError(
                f"mutual TLS is on but {', '.join(missing)} has no cert/key (or set "
                "zenoh.tls.mtls: false)"
            )

    def _check_ros2_sessions(self) -> None:
        """Under access control a robot's session may touch only the fleet's keys: its ROS 2
        traffic needs a session of its own (`ros2.endpoint`), or it would be refused unseen."""
        for machine_id in self.robot_ids:
            try:
                check_ros2_session(self, machine_id, self.machines[machine_id].source)
            except UserError as exc:
                raise ValueError(str(exc)) from None

    def ros2_for(self, machine_id: str | None) -> Ros2Config:
        """The ROS 2 settings of `machine_id`: its own `ros2` section over the fleet's."""
        machine = self.machines.get(machine_id) if machine_id is not None else None
        if machine is None or machine.ros2 is None:
            return self.ros2
        return machine.ros2.over(self.ros2)

    def uses_ros2(self, machine_id: str, source: str | SourceSpec | None = None) -> bool:
        """Whether robot `machine_id` takes part in ROS 2: a `ros2:` source (`source`, else its
        machine's) or results published on ROS 2 (its own or a service's)."""
        machine = self.machines[machine_id]
        if isinstance(parse_source(source or machine.source), Ros2Spec):
            return True
        if machine.results.ros2 is not None:
            return True
        return any(
            svc.results is not None and svc.results.ros2 is not None
            for name, svc in self.services.items()
            if name in self.services_of(machine_id)
        )

    def _tls_owners(self) -> list[tuple[str, TlsConfig]]:
        """Each daemon host's merged TLS settings, named by where they are written."""
        owners = [("registry", self.tls_for(self.registry.id))]
        owners += [(f"machines.{m}", self.tls_for(m)) for m in self.machines]
        return owners

    def _one_form(self) -> None:
        """The one-service form becomes a fleet of one service; with `services`, `service` and
        `model` are read back as the first service's."""
        if not self.services:
            if self.service is None:
                raise ValueError("service: required key is missing (or list services:)")
            if self.model is None:
                raise ValueError("model: required key is missing (or list services:)")
            self.services = {self.service: ServiceConfig(model=self.model)}
            return
        given = [k for k in ("service", "model") if k in self.model_fields_set]
        if given:
            raise ValueError(
                f"{' and '.join(given)}: the one-service form; with services:, set each "
                "service's model or handler there"
            )
        self.service, first = next(iter(self.services.items()))
        self.model = first.model

    def _check_machine_services(self) -> None:
        known = ", ".join(self.services)
        for machine_id, machine in self.machines.items():
            if machine.services is None:
                continue
            for name in machine.services:
                if name not in self.services:
                    raise ValueError(
                        f"machines.{machine_id}.services: unknown service {name!r}; "
                        f"services: {known}"
                    )
            twice = sorted({n for n in machine.services if machine.services.count(n) > 1})
            if twice:
                raise ValueError(f"machines.{machine_id}.services: names {', '.join(twice)} twice")

    def _check_initial_policy(self) -> None:
        known = ", ".join(self.machines) or "none"
        for machine_id, entry in self.initial_policy.items():
            machine = self.machines.get(machine_id)
            if machine is None:
                raise ValueError(
                    f"initial_policy: unknown machine {machine_id!r}; known machines: {known}"
                )
            if machine.role is Role.ROBOT and entry != ROBOT_STATE:
                raise ValueError(
                    f"initial_policy.{machine_id}: a robot's state is 'robot', "
                    f"not {_entry_text(entry)}"
                )
            if machine.role is Role.CLOUD and entry == ROBOT_STATE:
                raise ValueError(
                    f"initial_policy.{machine_id}: a cloud is 'service' or 'standby', not 'robot'"
                )
            if isinstance(entry, dict):
                for robot in entry:
                    if robot not in self.robot_ids:
                        raise ValueError(
                            f"initial_policy.{machine_id}: {robot!r} is not a robot of this "
                            f"fleet; robots: {', '.join(self.robot_ids) or 'none'}"
                        )
        single = len(self.services) == 1
        for name in self.services:
            offered = self.deployments_of(name)
            if not offered and not single:
                continue  # no cloud serves it: its robots run it themselves (a warning at start)
            for robot in self.robots_of(name):
                serving = [
                    d for d in offered if self.initial_state(d, robot) is DeploymentState.SERVICE
                ]
                if len(serving) != 1:
                    found = ", ".join(serving) if serving else "none"
                    of = "" if single else f" for service {name!r}"
                    raise ValueError(
                        f"initial_policy: robot {robot!r} needs exactly one cloud in service"
                        f"{of} at start, found {found}"
                    )

    def _resolve_paths(self, base: Path) -> None:
        def resolve(value: str | None) -> str | None:
            if value is None:
                return None
            try:
                return str((base / Path(value).expanduser()).resolve())
            except RuntimeError:  # `~name/...` of a user this host does not have
                raise ValueError(f"{value!r}: cannot expand '~' (no such user here)") from None

        for svc in self.services.values():
            if svc.model is not None and not svc.model.startswith(ZOO_PREFIX):
                svc.model = str(resolve(svc.model))
        self.model = next(iter(self.services.values())).model
        self.registry.db = resolve(self.registry.db or f"{self.fleet}.rib.sqlite")
        tls_sections = [self.zenoh.tls, self.registry.tls, self.cli.tls]
        tls_sections += [m.tls for m in self.machines.values()]
        for tls in tls_sections:
            if tls is not None:
                tls.ca, tls.cert, tls.key = resolve(tls.ca), resolve(tls.cert), resolve(tls.key)
        for machine in self.machines.values():
            machine.providers = [p.with_paths(resolve) for p in machine.providers]
            machine.source = str(parse_source(machine.source).resolved(lambda p: str(resolve(p))))

    # -- helpers -----------------------------------------------------------------------------------
    @property
    def source_path(self) -> Path | None:
        """The file this config was loaded from (None if built in memory)."""
        return self._source

    @property
    def robot_ids(self) -> list[str]:
        """Robot machine ids, in file order."""
        return [i for i, m in self.machines.items() if m.role is Role.ROBOT]

    @property
    def deployment_ids(self) -> list[str]:
        """Cloud machine (deployment) ids, in file order."""
        return [i for i, m in self.machines.items() if m.role is Role.CLOUD]

    # -- services --------------------------------------------------------------------------------
    def services_of(self, machine_id: str) -> list[str]:
        """The services machine `machine_id` serves (a cloud) or uses (a robot), in file order."""
        named = self.machines[machine_id].services
        return list(self.services) if named is None else [n for n in self.services if n in named]

    def deployments_of(self, service: str) -> list[str]:
        """The deployments that serve `service`, in file order."""
        return [d for d in self.deployment_ids if service in self.services_of(d)]

    def robots_of(self, service: str) -> list[str]:
        """The robots that use `service`, in file order."""
        return [r for r in self.robot_ids if service in self.services_of(r)]

    @property
    def service_config(self) -> ServiceConfig:
        """The service of a one-service fleet or of a service's view (`for_service`): the
        first service otherwise."""
        return self.services[self.service_name]

    @property
    def service_name(self) -> str:
        """The (first) service's name."""
        return next(iter(self.services))

    @property
    def model_spec(self) -> str:
        """The (first) service's model, a path or zoo:NAME; UserError for a handler's service
        (it has no ONNX model to split)."""
        model = self.service_config.model
        if model is None:
            raise UserError(
                f"service {self.service_name!r} is a handler ({self.handler}), not an ONNX model"
            )
        return model

    @property
    def runs(self) -> str:
        """What the (first) service runs, for people: its model (a path or zoo:NAME) or its
        handler (module:function)."""
        svc = self.service_config
        return svc.model if svc.model is not None else str(svc.handler)

    @property
    def handler(self) -> str | None:
        """The (first) service's handler, module:function (None: it is a model)."""
        return self.service_config.handler

    def service_for(self, name: str | None) -> str:
        """A wire message's `service` (None: a peer of a one-service fleet, meaning the first
        service); UserError naming the known services when this fleet has none of that name."""
        if name is None:
            return self.service_name
        if name not in self.services:
            raise UserError(
                f"unknown service {name!r}; this fleet's services: {', '.join(self.services)}"
            )
        return name

    def for_service(self, name: str) -> FleetConfig:
        """The fleet as one service sees it: a one-service fleet of `name`, with the service's
        overrides in place of the fleet-level keys, and only the machines that serve or use it
        (a robot's `fps` and `results` replaced by the service's where it sets them). The
        daemons run one plane per service on such views."""
        svc = self.services[self.service_for(name)]
        machines: dict[str, MachineConfig] = {}
        for machine_id, machine in self.machines.items():
            if name not in self.services_of(machine_id):
                continue
            update: dict[str, Any] = {"services": [name]}
            if machine.role is Role.ROBOT:
                if svc.fps is not None:
                    update["fps"] = svc.fps
                if svc.results is not None:
                    update["results"] = svc.results
            machines[machine_id] = machine.model_copy(update=update)
        initial: dict[str, Any] = {}
        for machine_id, entry in self.initial_policy.items():
            if machine_id in machines:
                initial[machine_id] = (
                    {r: st for r, st in entry.items() if r in machines}
                    if isinstance(entry, dict)
                    else entry
                )
        view = self.model_copy(
            update={
                "service": name,
                "model": svc.model,
                "services": {name: svc},
                "machines": machines,
                "initial_policy": initial,
                "input_shape": svc.input_shape if svc.input_shape is not None else self.input_shape,
                "cuts": svc.cuts or self.cuts,
                "policy": svc.policy or self.policy,
                "dispatch": svc.dispatch or self.dispatch,
                "latency_bound": svc.latency_bound or self.latency_bound,
                "deadline_s": svc.deadline_s or self.deadline_s,
                "objective": svc.objective or self.objective,
            }
        )
        view._source = self._source
        view._not_serving = frozenset(self.deployment_ids) - frozenset(self.deployments_of(name))
        return view

    @property
    def not_serving(self) -> frozenset[str]:
        """A service's view: the fleet's deployments that do not serve it (a robot does not
        probe them for it); empty for a whole fleet."""
        return self._not_serving

    def short_of_in_flight(self, in_flight: int) -> dict[str, int]:
        """The deployments that admit fewer of one robot's requests at once than a robot with
        `in_flight` frames in flight sends them (in round robin each member gets its share of
        the pool's), with what they admit (`batching.max_in_flight_per_robot`)."""
        clouds = self.deployment_ids
        members = min(self.dispatch.pool_limit() or len(clouds), len(clouds)) or 1
        each = math.ceil(in_flight / members)
        limits = {c: self.machines[c].batching.max_in_flight_per_robot for c in clouds}
        return {c: limit for c, limit in limits.items() if limit < each}

    @property
    def zoo_model(self) -> str | None:
        """The (first) service's zoo model name for `model: zoo:NAME`, else None."""
        return self.service_config.zoo_model

    @property
    def zoo_options(self) -> dict[str, float]:
        """The build options of the fleet's zoo models (`common.models.resolve_model`): the
        `nav.camera` geometry, which zoo:stereo takes and the other zoo models ignore."""
        return self.nav.camera.zoo_options()

    @property
    def tls(self) -> bool:
        """Whether this fleet uses TLS (a CA or a certificate is set anywhere)."""
        sections = [self.zenoh.tls, self.registry.tls, self.cli.tls]
        sections += [m.tls for m in self.machines.values()]
        return any(t is not None and t.configured for t in sections)

    @property
    def mtls(self) -> bool:
        """Whether links are mutual TLS: on by default whenever TLS is on."""
        explicit = self.zenoh.tls.mtls
        return self.tls if explicit is None else explicit and self.tls

    @property
    def access_control(self) -> bool:
        """Whether every session enforces the generated access control (common/acl.py): by
        default whenever links are mutual TLS and each host has a certificate of its own (one
        shared certificate cannot tell the hosts apart)."""
        explicit = self.zenoh.access_control
        if explicit is None:
            return self.mtls and self.zenoh.tls.cert is None
        return explicit

    def tls_for(self, identity: str | None) -> TlsConfig:
        """The TLS settings of one host: its own section (`registry.tls` for the registry's id,
        `cli.tls` for `cli`, else `machines.<id>.tls`) over `zenoh.tls`; `mtls` resolved."""
        base = self.zenoh.tls
        own: TlsConfig | None = None
        if identity is not None:
            if identity == self.registry.id:
                own = self.registry.tls
            elif identity == CLI_IDENTITY:
                own = self.cli.tls
            elif identity in self.machines:
                own = self.machines[identity].tls
        merged = base.model_copy()
        if own is not None:
            for name in ("ca", "cert", "key", "mtls"):
                value = getattr(own, name)
                if value is not None:
                    setattr(merged, name, value)
        merged.mtls = self.mtls if own is None or own.mtls is None else own.mtls
        return merged

    @property
    def model_path(self) -> Path | None:
        """The (first) service's model file (absolute) when it is a path, else None (a zoo
        model or a handler)."""
        model = self.service_config.model
        return None if model is None or self.zoo_model is not None else Path(model)

    @property
    def db_path(self) -> Path:
        """The registry's sqlite file (absolute)."""
        return Path(self.registry.db or f"{self.fleet}.rib.sqlite")

    def machine(self, machine_id: str, role: Role | None = None) -> MachineConfig:
        """The machine `machine_id`; UserError listing the known ids if there is none (or if it
        does not have `role`)."""
        where = str(self._source) if self._source else "the fleet config"
        machine = self.machines.get(machine_id)
        if machine is None:
            known = ", ".join(self.machines) or "none"
            raise UserError(f"no machine {machine_id!r} in {where}; known machines: {known}")
        if role is not None and machine.role != role:
            same = ", ".join(i for i, m in self.machines.items() if m.role == role) or "none"
            raise UserError(
                f"{machine_id!r} is a {machine.role} machine in {where}, not a {role}; "
                f"{role} machines: {same}"
            )
        return machine

    def initial_state(self, deployment: str, robot: str) -> DeploymentState:
        """SERVICE or STANDBY: the state of cloud `deployment` for `robot` at start (a machine
        initial_policy does not list is standby)."""
        entry = self.initial_policy.get(deployment, DeploymentState.STANDBY)
        if isinstance(entry, dict):
            return entry.get(robot, DeploymentState.STANDBY)
        if isinstance(entry, DeploymentState):
            return entry
        return DeploymentState.STANDBY  # `robot`: a robot serves nobody

    def initial_service(self, robot: str) -> str | None:
        """The deployment serving `robot` at start (None when the fleet has no cloud for it)."""
        for deployment in self.deployment_ids:
            if self.initial_state(deployment, robot) is DeploymentState.SERVICE:
                return deployment
        return None


def _base_dir(info: ValidationInfo) -> Path:
    context = info.context if isinstance(info.context, dict) else {}
    base = context.get("base_dir")
    return Path(base) if base is not None else Path.cwd()


def load_fleet(path: str | Path) -> FleetConfig:
    """Read and check a fleet.yaml; UserError (one line, file and field) on any problem."""
    path = Path(path)
    data = read_yaml(path, missing="no such file (create one with `elasticfog init DIR`)")
    return fleet_from_dict(data, source=path)


def fleet_from_dict(data: Any, *, source: str | Path | None = None) -> FleetConfig:
    """Check an already-parsed fleet mapping; relative paths are relative to `source`'s folder
    (the working directory without a source)."""
    name = str(source) if source is not None else "fleet config"
    if data is None:
        raise UserError(f"{name}: the file is empty; expected a mapping with service, model, ...")
    if not isinstance(data, dict):
        raise UserError(f"{name}: expected a mapping at the top level, got {type(data).__name__}")
    base = Path(source).resolve().parent if source is not None else Path.cwd()
    try:
        config = FleetConfig.model_validate(data, context={"base_dir": base})
    except ValidationError as exc:
        raise UserError(f"{name}: {format_validation_error(exc, FleetConfig)}") from None
    config._source = Path(source) if source is not None else None
    return config


def check_ros2_session(
    cfg: FleetConfig,
    robot: str,
    source: str | SourceSpec | None = None,
    results_ros2: str | None = None,
) -> None:
    """A UserError when robot `robot` would take part in ROS 2 (a `ros2:` source, `source` or
    its machine's; ROS 2 results, `results_ros2` or the file's) on a fleet session under access
    control: that session may touch only `ef/<fleet>/**`, so every camera frame and result would
    be refused without a word. Such a robot needs `ros2.endpoint`, a session of its own."""
    if not cfg.access_control or cfg.ros2_for(robot).endpoint is not None:
        return
    if results_ros2 is None and not cfg.uses_ros2(robot, source):
        return
    raise UserError(
        f"robot {robot} takes part in ROS 2 but the fleet's sessions are under access control "
        "(zenoh.access_control: only the fleet's keys pass): set ros2.endpoint (fleet-wide or "
        f"in machines.{robot}.ros2) to the ROS 2 graph's router, e.g. tcp/127.0.0.1:7447 (the "
        "robot host's rmw_zenohd); the robot then speaks ROS 2 on a session of its own"
    )
