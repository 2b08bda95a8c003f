"""Fixtures for every test tier.

- `isolated_cache` (autouse, whole session): ``ELASTICFOG_CACHE_DIR`` points at a fresh temporary
  directory, so tests never read or fill the user's model cache, and daemons started as
  subprocesses inherit the same cache.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

CACHE_DIR_ENV = "ELASTICFOG_CACHE_DIR"


@pytest.fixture(scope="session", autouse=True)
def isolated_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A per-session model cache directory, set in the environment for the whole run."""
    previous = os.environ.get(CACHE_DIR_ENV)
    path = tmp_path_factory.mktemp("elasticfog-cache")
    os.environ[CACHE_DIR_ENV] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop(CACHE_DIR_ENV, None)
        else:
            os.environ[CACHE_DIR_ENV] = previous
