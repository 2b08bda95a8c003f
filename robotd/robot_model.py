"""The robot's split model as its frame loop uses it.

`open_split_model` loads the fleet's model at startup: its partition at the configured cuts, as
one set of shared-weight onnxruntime sessions for this machine (the full model and every cut's
prefix and suffix; not the segments, which only the cloud runs), which the caller hands to the
lifecycle, which closes it. `RobotModel` is what the loop needs around those sessions: the
camera inputs (`common.image_input.ImageInputs`: one image, or the views of a stereo pair matched
by name, and the source opened for them), the startup profile the
policies start from (`robotd.robot_profile`), the position of each cut index in the partition,
and the check of a cloud reply against the model's outputs (a reply that
lacks one is a decode error: the robot finishes the frame itself).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from common.config import FleetConfig, MachineConfig
from common.errors import UserError
from common.fleet_model import fleet_split_model
from common.image_input import ImageInputs
from common.partition import sample_feeds
from common.partition.runtime import SplitModel
from common.providers import enforce, ort_providers, prepare
from common.source_spec import SourceSpec
from common.wire.telemetry import FallbackReason
from robotd.frame_path.offload import CallResult
from robotd.policies import Decision
from robotd.robot_profile import StartProfile, measured_profile
from robotd.sources.frame_sources import FrameSource, SourceSession
from robotd.sources.opening import open_source_for
from robotd.sources.stereo_frame import CameraFrame, StereoFrame
from robotd.sources.stereo_geometry import model_camera


def open_split_model(
    config: FleetConfig, machine: MachineConfig, *, who: str = "robot"
) -> SplitModel:
    """The fleet's model, partitioned at its cuts, as sessions on `machine`'s providers; a
    session that did not get an accelerator asked for is a one-line UserError (or, with
    `providers_fallback: allow`, a warning: `common.providers.enforce`).

    The segments' sessions are not built: the robot runs a segment's tail as the suffix of its
    end cut, never the segment itself (with zoo:stereo at 640x480 they held ~140 MB)."""
    prepare(machine.providers)
    model = fleet_split_model(
        config,
        providers=ort_providers(machine.providers),
        threads=machine.threads or None,
        segments=False,
    )
    try:
        enforce(
            model.session_providers(),
            machine.providers,
            machine.providers_fallback,
            who=who,
        )
    except UserError:
        model.close()
        raise
    return model


class RobotModel:
    """`RobotModel(model, name)`: UserError unless every input of `model` (called `name` in
    messages) is an image the robot can feed: one camera frame, or the views of a stereo one."""

    def __init__(self, model: SplitModel, name: str) -> None:
        specs = model.input_specs()
        self.model = model
        self.inputs = ImageInputs(specs, name)
        # Input of the model's shape and type, for the warm-up and the startup profile.
        self.sample_feeds = sample_feeds(specs)
        self._position = {cut.index: k for k, cut in enumerate(model.partition.cuts)}

    def profile(
        self,
        config: FleetConfig,
        *,
        source_spec: str | SourceSpec,
        seed: int,
        threads: int,
        policy_spec: str,
    ) -> StartProfile:
        """This robot's profile, measured here (`robotd.robot_profile.measured_profile`), and
        what measures its codecs on the first frames served when its source has none yet."""
        return measured_profile(
            self.model,
            self.sample_feeds,
            config=config,
            inputs=self.inputs,
            source_spec=source_spec,
            seed=seed,
            threads=threads,
            policy_spec=policy_spec,
        )

    def open_source(
        self, spec: str | SourceSpec, *, seed: int, session: SourceSession | None = None
    ) -> FrameSource:
        """The frame source `spec` at the model's input size (one fed over Zenoh on the
        daemon's `session`); a one-line UserError when its views do not match the model's
        image inputs. A stereo model's source is told the camera the model was built for (its
        metadata `nav.camera`): a ROS 2 camera with another geometry is named in a warning."""
        built_for = model_camera(self.model.partition.full) if self.inputs.views else None
        return open_source_for(spec, self.inputs, seed=seed, session=session, built_for=built_for)

    def feeds(self, frame: CameraFrame) -> dict[str, np.ndarray]:
        """The model's input for camera frame `frame` (an image, or a stereo frame's views)."""
        return self.inputs.feeds(frame.views if isinstance(frame, StereoFrame) else frame)

    def position_of(self, decision: Decision, policy: str) -> int:
        """The partition position of the cut `decision` chose; a UserError naming `policy` and
        the model's cuts when it has no such cut."""
        try:
            return self._position[int(decision.action)]
        except (KeyError, ValueError):
            known = ", ".join(str(i) for i in self._position)
            raise UserError(
                f"policy {policy} chose cut {decision.action!r}; this model has cuts {known}"
            ) from None

    def checked(self, result: CallResult, end: int | None = None) -> CallResult:
        """`result`, or a decode error when its reply lacks an output of the model (or, for a
        segment up to cut `end`, a tensor of that cut): the frame is then finished on the robot."""
        reply = result.reply
        if reply is None:
            return result
        names = self.model.output_names if end is None else self.model.partition.cut(end).tensors
        missing = [n for n in names if n not in reply.outputs]
        if not missing:
            return result
        return dataclasses.replace(
            result,
            reply=None,
            reason=FallbackReason.DECODE_ERROR,
            detail=f"reply from {reply.deployment} lacks output(s) {', '.join(missing)}",
        )
