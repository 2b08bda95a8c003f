"""Gates of tests that need what not every machine gives: root for the namespace testbed."""

from __future__ import annotations

import os

import pytest

ROOT_REASON = "needs root: creates network namespaces, tc qdiscs and cgroups"

root_only = pytest.mark.skipif(os.geteuid() != 0, reason=ROOT_REASON)
"""Skip unless root (the testbed's namespaces, qdiscs and cgroups)."""
