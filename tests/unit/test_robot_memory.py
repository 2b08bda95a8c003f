"""What the robot's memory at startup relies on: it builds no segment sessions (only the cloud
runs segments; each held tens of MB with zoo:stereo at 640x480), a segment left out is still
built when asked for, and glibc's trim gives freed heap memory back (`common.heap`)."""

from __future__ import annotations

import ctypes
import sys
from pathlib import Path

import numpy as np
import pytest

from common.config import fleet_from_dict
from common.heap import can_trim, trim_heap
from common.partition import sample_feeds, split_model
from common.partition.runtime import SplitModel
from robotd.robot_model import open_split_model
from tests.helpers.onnx_graphs import residual, save

HEAP_BLOCK_BYTES = 64 * 1024
"""Below glibc's mmap threshold (128 KiB at start), so the blocks come from the heap."""
HEAP_BLOCKS = 256


def test_the_robot_builds_the_full_model_prefixes_and_suffixes_but_no_segment(
    tmp_path: Path,
) -> None:
    cfg = fleet_from_dict(
        {
            "service": "vision",
            "model": str(save(residual(), tmp_path / "m.onnx")),
            "cuts": {"segments": True},
            "machines": {"edge-1": {"role": "cloud"}, "robot-1": {"role": "robot"}},
            "initial_policy": {"edge-1": "service"},
            "latency_bound": {"seconds": 0.5},
            "deadline_s": 1.0,
        }
    )
    with open_split_model(cfg, cfg.machine("robot-1"), who="robot-1") as model:
        assert model.partition.segments, "the split has segments to leave out"
        built = set(model.session_providers())
        expected = {"the full model"}
        for k, cut in enumerate(model.partition.cuts):
            expected.add(f"suffix of cut {k}")
            if cut.prefix is not None:
                expected.add(f"prefix of cut {k}")
        assert built == expected


def test_a_segment_left_out_at_construction_is_built_on_first_use(tmp_path: Path) -> None:
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    model = SplitModel(part, segments=False)
    everything = SplitModel(part)
    seg = part.segments[0]
    assert not any(what.startswith("segment") for what in model.session_providers())
    assert f"segment {seg.start}-{seg.end}" in everything.session_providers()
    feeds = sample_feeds(model.input_specs(), seed=5)
    sent = model.run_prefix(seg.start, feeds)
    got = model.run_segment(seg.start, seg.end, sent)
    want = everything.run_segment(seg.start, seg.end, sent)
    for name, value in want.items():
        np.testing.assert_array_equal(got[name], value)
    assert f"segment {seg.start}-{seg.end}" in model.session_providers()


@pytest.mark.skipif(not sys.platform.startswith("linux") or not can_trim(), reason="glibc only")
def test_trim_returns_freed_heap_memory_that_free_keeps() -> None:
    """Blocks freed below a live one stay in the heap (free only trims its top): the trim is
    what gives them back. Guards the robot's startup, whose freed tensors stayed resident."""
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    blocks = [libc.malloc(HEAP_BLOCK_BYTES) for _ in range(HEAP_BLOCKS)]
    assert all(blocks)
    for block in blocks:
        ctypes.memset(block, 1, HEAP_BLOCK_BYTES)  # resident, as a run's tensors are
    last = blocks.pop()
    trim_heap()  # what earlier tests left free, so that the next trim has only these
    for block in blocks:
        libc.free(block)
    try:
        assert trim_heap()
    finally:
        libc.free(last)
