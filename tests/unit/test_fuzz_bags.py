"""Fuzzing the `bag:` source (robotd/sources/bag.py): damaged bag files and damaged records.

Inputs: the storage file of a small recording (MCAP, sqlite3) with its bytes overwritten, inserted,
deleted or cut; recordings whose records hold any bytes (valid CDR corrupted, cut, another
type's message, random bytes). Whatever the input, opening either works or raises the named
`NotABag`/`BagTopicError` (a `SourceError`) with a one-line message; reading gives BGR frames until
`EndOfStream`, within a time bound; every record is either a frame or counted as refused, never
lost silently. Records are read within a memory bound too; a damaged file is not: rosbags' MCAP
reader asks Python for a damaged length field's bytes at once (a 28 MB claim in a 14 KB file is
a 28 MB `read`, a 1 TB claim a MemoryError, which the source names), memory the kernel never
backs, and a bag is the robot's own file, not network input.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from common import ros2_messages as rm
from common.source_spec import SourceError
from robotd.sources.bag import BagSource
from robotd.sources.frame_sources import EndOfStream
from tests.unit.bag_support import (
    STORAGES,
    Record,
    camera_records,
    photo_frames,
    storage_file,
    write_bag,
)
from tests.unit.fuzz_support import budget, byte_edits, mutate, run_decoder

FRAMES = 3
# Far more reads than any bag here holds: a source that never ends fails the test.
MAX_READS = 100
# Reading a few-KiB bag may hold the file, a decoded chunk and a few frames of 32×40.
MEMORY_BYTES = 8 * 1024 * 1024


@functools.cache
def recorded(storage: str, compressed: bool) -> bytes:
    """The storage file of a small recording, written once per process."""
    with tempfile.TemporaryDirectory() as tmp:
        frames = photo_frames(FRAMES, 32, 40)
        bag = write_bag(Path(tmp) / "run", camera_records(frames, compressed=compressed), storage)
        return storage_file(bag).read_bytes()


def read_bag(path: Path, *, bounded: bool = True) -> tuple[int, int] | None:
    """(frames, refused) of the bag at `path`, or None where it was refused at open; within the
    memory bound unless not `bounded`."""

    def read() -> tuple[int, int]:
        with BagSource(path) as source:
            for frames in range(MAX_READS):  # frames read so far
                source.next_offset_s()
                try:
                    frame = source.read()
                except EndOfStream:
                    return frames, source.refused
                assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8
                assert frame.ndim == 3 and frame.shape[2] == 3
        raise AssertionError(f"the bag did not end after {MAX_READS} reads")

    return run_decoder(read, (SourceError,), max_bytes=MEMORY_BYTES if bounded else None)


@budget(40)
@given(
    storage=st.sampled_from(STORAGES),
    compressed=st.booleans(),
    edits=byte_edits,
    keep=st.none() | st.integers(0, 2**16),
)
def test_damaged_bag_files(
    storage: str, compressed: bool, edits: list[tuple[int, int, bytes]], keep: int | None
) -> None:
    data = mutate(recorded(storage, compressed), edits)
    if keep is not None:
        data = data[: keep % (len(data) + 1)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"run.{'mcap' if storage == 'mcap' else 'db3'}"
        path.write_bytes(data)
        read_bag(path, bounded=False)


_payloads = st.one_of(
    st.binary(max_size=64),
    st.tuples(st.booleans(), byte_edits).map(
        lambda c: mutate(camera_records(photo_frames(1, 8, 8), compressed=c[0])[0].payload, c[1])
    ),
    st.just(rm.encode_twist(rm.Twist())),
    st.just(rm.encode_float32_multi_array(np.zeros((2, 2), np.float32))),
)


@budget(25)
@given(storage=st.sampled_from(STORAGES), payloads=st.lists(_payloads, min_size=1, max_size=4))
def test_records_of_any_bytes_are_frames_or_counted(storage: str, payloads: list[bytes]) -> None:
    good = camera_records(photo_frames(2, 8, 8))
    odd = [Record(good[0].topic, good[0].msgtype, 0, p) for p in payloads]
    records = [good[0], *odd, good[1]]
    records = [Record(r.topic, r.msgtype, i * 1000, r.payload) for i, r in enumerate(records)]
    with tempfile.TemporaryDirectory() as tmp:
        result = read_bag(write_bag(Path(tmp) / "run", records, storage))
    assert result is not None
    frames, refused = result
    assert frames >= 2 and frames + refused == len(records)
