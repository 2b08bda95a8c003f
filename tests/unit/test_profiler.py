"""The profiler: the contract JSON, FLOPs per side, and the cache keyed by model digest."""

from __future__ import annotations

from pathlib import Path

import pytest

from common import profiler
from common.errors import UserError
from common.models import file_digest
from common.profiler import profile_model
from tests.helpers.onnx_graphs import matmul_chain, residual, save

CUT_KEYS = {"index", "tensors", "bytes", "prefix_ms", "suffix_ms", "prefix_flops", "suffix_flops"}


def test_profile_is_the_contract_json(tmp_path: Path) -> None:
    src = save(matmul_chain(2, 16, out_dim=4), tmp_path / "m.onnx")
    prof = profile_model(str(src), runs=3, threads=1)
    assert set(prof) == {"digest", "full_ms", "cuts"}
    assert prof["digest"] == file_digest(src)
    assert prof["full_ms"] > 0
    assert [c["tensors"] for c in prof["cuts"]] == [["x"], ["r0"], ["m1"]]
    for k, cut in enumerate(prof["cuts"]):
        assert set(cut) == CUT_KEYS
        assert cut["index"] == k
        assert cut["bytes"] == (64 if k < 2 else 16)
        assert cut["suffix_ms"] > 0
    assert prof["cuts"][0]["prefix_ms"] == 0.0  # nothing runs on the robot for cut 0
    assert prof["cuts"][1]["prefix_ms"] > 0
    # 1x16 @ 16x16 then 1x16 @ 16x4, two FLOPs per multiply-add
    assert [(c["prefix_flops"], c["suffix_flops"]) for c in prof["cuts"]] == [
        (0, 512 + 128),
        (512, 128),
        (512 + 128, 0),
    ]


def test_second_profile_reads_the_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = save(residual(), tmp_path / "m.onnx")
    first = profile_model(src, runs=2)

    def must_not_measure(*args: object) -> None:
        raise AssertionError("measured again instead of reading the cache")

    monkeypatch.setattr(profiler, "_measure", must_not_measure)
    assert profile_model(src, runs=2) == first
    # other runs or threads are another measurement
    with pytest.raises(AssertionError, match="measured again"):
        profile_model(src, runs=2, threads=1)
    with pytest.raises(AssertionError, match="measured again"):
        profile_model(src, runs=2, refresh=True)


def test_changed_model_is_profiled_again(tmp_path: Path) -> None:
    src = tmp_path / "m.onnx"
    first = profile_model(save(matmul_chain(2, 8), src), runs=2)
    second = profile_model(save(matmul_chain(3, 8), src), runs=2)
    assert first["digest"] != second["digest"]
    assert len(second["cuts"]) > len(first["cuts"])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"runs": 0}, "--runs must be"), ({"threads": 0}, "--threads must be")],
)
def test_bad_options(tmp_path: Path, kwargs: dict[str, int], message: str) -> None:
    src = save(residual(), tmp_path / "m.onnx")
    with pytest.raises(UserError, match=message):
        profile_model(src, **kwargs)  # type: ignore[arg-type]
