"""The registry's garbage-collector setting: its youngest generation is collected every
GC_YOUNG_THRESHOLD allocations (a round's short-lived objects are gone before a collection
could promote them; docs/scale.md), a higher setting of an embedding process is kept, and the
older generations' settings are left as they were."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from registry.daemon import GC_YOUNG_THRESHOLD, tune_collector


@pytest.fixture(autouse=True)
def _restore_thresholds() -> Iterator[None]:
    saved = gc.get_threshold()
    yield
    gc.set_threshold(*saved)


def test_the_youngest_generation_is_collected_less_often() -> None:
    gc.set_threshold(700, 10, 10)
    tune_collector()
    assert gc.get_threshold() == (GC_YOUNG_THRESHOLD, 10, 10)


def test_a_higher_setting_and_the_older_generations_are_kept() -> None:
    gc.set_threshold(GC_YOUNG_THRESHOLD * 2, 5, 7)
    tune_collector()
    assert gc.get_threshold() == (GC_YOUNG_THRESHOLD * 2, 5, 7)
