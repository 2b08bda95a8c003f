"""The objective a policy minimises: a weighted sum of latency, robot CPU, robot energy and bytes.

Energy comes from a simple additive power model: the robot draws `idle_w` for the whole frame,
`busy_w - idle_w` more while it computes and `tx_w - idle_w` more while its radio moves the frame.
With the default weights (latency 1, the rest 0) the cost of a frame is its latency in seconds.

The learners split a frame's cost into a part the robot knows (its own compute, bytes sent) and
the cloud-side part they learn (waiting for the reply, radio time), which stays linear in the
context vector whatever the weights.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from common.errors import UserError
from common.yaml_files import format_validation_error
from robotd.policies.base import FloatArray

F = TypeVar("F", float, FloatArray)


def cloud_cost(
    wait_rate: float, radio_rate: float, cloud_s: float, cloud_compute_s: float | None
) -> float:
    """`Objective.cloud_part` from the objective's rates (the learners cache them: this runs
    every offloaded frame)."""
    if cloud_compute_s is None:
        return wait_rate * cloud_s + radio_rate * cloud_s
    compute = cloud_compute_s if cloud_compute_s < cloud_s else cloud_s
    return wait_rate * cloud_s + radio_rate * (cloud_s - compute)


class PowerModel(BaseModel):
    """Robot power draw in watts, for the energy estimate."""

    model_config = ConfigDict(extra="forbid")

    idle_w: float = Field(default=2.0, ge=0, description="Power while idle or waiting, W.")
    busy_w: float = Field(default=7.0, ge=0, description="Power while computing, W.")
    tx_w: float = Field(default=4.0, ge=0, description="Power while the radio sends/receives, W.")

    @model_validator(mode="after")
    def _above_idle(self) -> PowerModel:
        if self.busy_w < self.idle_w:
            raise ValueError(f"busy_w ({self.busy_w}) must be >= idle_w ({self.idle_w})")
        if self.tx_w < self.idle_w:
            raise ValueError(f"tx_w ({self.tx_w}) must be >= idle_w ({self.idle_w})")
        return self


class Objective(BaseModel):
    """Weights of the per-frame cost; units: per second, per CPU-second, per joule, per MB."""

    model_config = ConfigDict(extra="forbid")

    latency: float = Field(default=1.0, ge=0, description="Weight of end-to-end latency, per s.")
    cpu: float = Field(default=0.0, ge=0, description="Weight of robot CPU time, per CPU-second.")
    energy: float = Field(default=0.0, ge=0, description="Weight of robot energy, per joule.")
    bytes: float = Field(default=0.0, ge=0, description="Weight of bytes sent, per MB.")
    power: PowerModel = Field(default_factory=PowerModel, description="Robot power model.")

    @model_validator(mode="after")
    def _some_weight(self) -> Objective:
        if self.latency == 0 and self.cpu == 0 and self.energy == 0 and self.bytes == 0:
            raise ValueError("at least one of latency, cpu, energy, bytes must be > 0")
        return self

    @classmethod
    def parse(cls, value: Objective | Mapping[str, Any] | None) -> Objective:
        """An Objective from a config dict (or None for the default); UserError on bad keys."""
        if value is None:
            return cls()
        if isinstance(value, Objective):
            return value
        if not isinstance(value, Mapping):
            raise UserError(f"objective: expected a mapping, got {type(value).__name__}")
        try:
            return cls.model_validate(dict(value))
        except ValidationError as exc:
            raise UserError(f"objective: {format_validation_error(exc, cls)}") from None

    @property
    def robot_rate(self) -> float:
        """Cost of one second of robot compute (latency, CPU and busy power all run)."""
        return self.latency + self.cpu + self.energy * self.power.busy_w

    @property
    def wait_rate(self) -> float:
        """Cost of one second spent waiting for the cloud."""
        return self.latency + self.energy * self.power.idle_w

    @property
    def radio_rate(self) -> float:
        """Extra cost of one second of radio activity."""
        return self.energy * (self.power.tx_w - self.power.idle_w)

    def energy_j(self, latency_s: F, cpu_s: F, radio_s: F) -> F:
        """Robot energy of a frame, joules."""
        p = self.power
        return p.idle_w * latency_s + (p.busy_w - p.idle_w) * cpu_s + (p.tx_w - p.idle_w) * radio_s

    def frame_cost(self, latency_s: F, cpu_s: F, radio_s: F, mb: F) -> F:
        """Objective cost of a frame from its latency, CPU seconds, radio seconds and MB sent."""
        return (
            self.latency * latency_s
            + self.cpu * cpu_s
            + self.energy * self.energy_j(latency_s, cpu_s, radio_s)
            + self.bytes * mb
        )

    def cloud_part(self, cloud_s: float, cloud_compute_s: float | None) -> float:
        """The learned cloud-side cost of an offloaded frame (without its known bytes cost).

        The radio is counted active for the whole round trip except the server's compute time,
        when the reply says how long that was.
        """
        return cloud_cost(self.wait_rate, self.radio_rate, cloud_s, cloud_compute_s)
