"""The testbed's defaults that `elasticfog testbed` shows in its options.

They live apart from deploy.testbed (psutil, tc shaping, cgroups) so that building the CLI
imports none of it: `elasticfog --help` must stay fast.
"""

from __future__ import annotations

DEFAULT_NAME = "ef"
DEFAULT_HOSTS = ("registry", "robot", "edge-1", "edge-2", "cloud-1")
DEFAULT_SUBNET = "10.77.0.0/24"
NAME_ENV = "ELASTICFOG_TESTBED"
