"""Segments of a split (the part between two cuts) on tiny onnx.helper graphs: which are built,
what their boundaries are, that prefix → segment → suffix equals the full model, that a failing
segment is excluded with the reason, and that the manifest and the cache keep them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest

from common.partition import Partition, load_partition, sample_feeds, split_model
from common.partition.errors import CutError
from common.partition.graph import DataflowGraph
from common.partition.manifest import excluded_cut
from common.partition.runtime import SplitModel
from common.partition.segments import plan_segment
from tests.helpers.onnx_graphs import chain, late_input, residual, save


def pairs(part: Partition) -> list[tuple[int, int]]:
    return [(s.start, s.end) for s in part.segments]


def test_a_split_without_segments_has_none_and_its_manifest_no_field(tmp_path: Path) -> None:
    """Regression guard: splits made as before keep their manifest and options unchanged."""
    part = split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split")
    assert part.segments == []
    data = json.loads((tmp_path / "split" / "manifest.json").read_text())
    assert "segments" not in data and "segments" not in data["options"]
    with pytest.raises(ValueError, match="no segment from cut 0 to cut 1; this split has none"):
        part.segment(0, 1)


def test_every_pair_of_cuts_gets_a_verified_segment(tmp_path: Path) -> None:
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    n = len(part.cuts)
    assert pairs(part) == [(a, b) for a in range(n) for b in range(a + 1, n)]
    for seg in part.segments:
        assert seg.verified and seg.max_abs_err is not None and seg.max_abs_err <= 1e-5
        assert seg.path.name == f"cut{seg.start:03d}-{seg.end:03d}.segment.onnx"
        onnx.checker.check_model(str(seg.path))


def test_segment_boundaries_are_the_two_cuts_tensors(tmp_path: Path) -> None:
    """Inputs: the start cut's tensors the segment reads; outputs: the end cut's tensors it
    computes (a tensor crossing both cuts is passed through by the runtime)."""
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    # residual's cuts: [x], [a], [a, b], [a, c], [d]
    seg = onnx.load(str(part.segment(1, 3).path))
    assert [i.name for i in seg.graph.input] == ["a"]
    assert [o.name for o in seg.graph.output] == ["c"]
    assert sorted(n.op_type for n in seg.graph.node) == ["Abs", "Neg"]
    seg = onnx.load(str(part.segment(0, 4).path))
    assert [i.name for i in seg.graph.input] == ["x"]
    assert [o.name for o in seg.graph.output] == ["d"]


def test_prefix_segment_suffix_equals_the_full_model(tmp_path: Path) -> None:
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    model = SplitModel(part)
    feeds = sample_feeds(model.input_specs(), seed=3)
    [expected] = model.run_full(feeds).values()
    for seg in part.segments:
        middle = model.run_segment(seg.start, seg.end, model.run_prefix(seg.start, feeds))
        assert sorted(middle) == sorted(part.cuts[seg.end].tensors)
        [got] = model.run_suffix(seg.end, middle).values()
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_a_late_model_input_passes_through_the_segment(tmp_path: Path) -> None:
    """late_input's z crosses every cut: the segment neither reads nor computes it."""
    part = split_model(save(late_input(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    # cuts: [x, z], [z, a], [z, b]
    seg = onnx.load(str(part.segment(0, 2).path))
    assert [i.name for i in seg.graph.input] == ["x"]
    assert [o.name for o in seg.graph.output] == ["b"]
    model = SplitModel(part)
    feeds = sample_feeds(model.input_specs())
    middle = model.run_segment(0, 2, model.run_prefix(0, feeds))
    np.testing.assert_array_equal(middle["z"], feeds["z"])


def test_missing_start_tensors_are_named(tmp_path: Path) -> None:
    part = split_model(save(residual(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    with pytest.raises(ValueError, match=r"segment 2-4: missing tensor\(s\) b"):
        SplitModel(part).run_segment(2, 4, {"a": np.zeros((1, 4), np.float32)})


def test_cuts_in_the_wrong_order_are_not_a_segment(tmp_path: Path) -> None:
    graph = DataflowGraph(residual())
    later, earlier = excluded_cut(["d"], ""), excluded_cut(["a"], "")
    later.index, earlier.index = 4, 1
    with pytest.raises(CutError, match=r"needs model input\(s\) x that cut 4 does not carry"):
        plan_segment(graph, later, earlier)


def test_a_segment_that_fails_verification_is_excluded_with_the_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = SplitModel.run_segment

    def off_for_0_to_2(self: SplitModel, start: int, end: int, tensors, **kw):  # type: ignore[no-untyped-def]
        out = real(self, start, end, tensors, **kw)
        if (start, end) == (0, 2):
            out = {k: v + 1.0 for k, v in out.items()}
        return out

    monkeypatch.setattr(SplitModel, "run_segment", off_for_0_to_2)
    part = split_model(save(chain(), tmp_path / "m.onnx"), tmp_path / "split", segments=True)
    assert pairs(part) == [(0, 1), (1, 2)]
    [bad] = [c for c in part.excluded if "segment from cut 0 to cut 2" in c.reason]
    assert "verification failed" in bad.reason
    assert not (tmp_path / "split" / "cut000-002.segment.onnx").exists()


def test_segments_survive_the_manifest_and_have_their_own_cache_entry(tmp_path: Path) -> None:
    src = save(chain(), tmp_path / "m.onnx")
    plain = load_partition(src)
    with_segments = load_partition(src, segments=True)
    assert plain.dir != with_segments.dir and plain.segments == []
    again = load_partition(src, segments=True)
    assert again.dir == with_segments.dir
    assert pairs(again) == pairs(with_segments) == [(0, 1), (0, 2), (1, 2)]
    assert all(s.path.is_file() and s.verified for s in again.segments)
    assert Partition.load(again.dir).segments == again.segments
