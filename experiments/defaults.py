"""What the experiments run by default: the robot, its model and its camera image.

Apart from `fleet` and `options` so that `elasticfog bench --help` shows them without importing
the testbed.
"""

from __future__ import annotations

DEFAULT_MODEL = "zoo:mobilenet_v2"
DEFAULT_INPUT_SHAPE = (3, 240, 320)
"""A 320x240 camera image (uint8, 230 KB raw; about 5-8 KB as a JPEG of a photograph) into a
network built for robots: the whole model takes about 28 ms on one core of the testbed host."""
DEFAULT_ROBOT_CPU = 0.5
"""The robot's CPU quota in cores: MobileNetV2 at 320x240 then takes about 60 ms there."""
