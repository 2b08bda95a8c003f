"""`bench nav`'s fidelity rows: each image codec against raw on zoo:stereo, and the gate's verdict.

Real graph, real codecs, real onnxruntime, at a small size (rendered frames and the Motorcycle
pair resized), so the rows' shape and the gate's rules are checked without the testbed."""

from __future__ import annotations

import pytest

from common.codec_profile import Fidelity
from experiments.nav_fidelity import (
    CODECS,
    TOLERATED_BIN_REL_ERR,
    markdown,
    measure,
    summary,
)


@pytest.fixture(scope="module")
def rows() -> list[dict]:
    return measure(96, 64, 1)


def test_every_codec_on_rendered_frames_and_the_motorcycle_pair(rows: list[dict]) -> None:
    table = summary(rows)
    assert {(r["source"], r["codec"]) for r in table} == {
        (source, codec) for source in ("world", "motorcycle") for codec in CODECS
    }
    for r in table:
        assert r["size"] == "96x64" and r["bytes"] > 0
        if r["codec"] == "png":  # lossless: the answers are the raw ones
            assert r["d_coll_rel_err"] == 0.0 and r["disparity_bad1_share"] == 0.0
            assert r["passes"] and r["within_tolerance"]
    assert "| 96x64 | world (1) | png |" in markdown(table)


def test_the_verdict_follows_the_bound(rows: list[dict]) -> None:
    loose = summary(rows, Fidelity(max_output_rel_err=1e9))
    assert all(r["passes"] for r in loose)
    strict = summary(rows, Fidelity(max_output_rel_err=1e-12))
    assert {r["codec"] for r in strict if r["passes"]} >= {"png"}
    assert all(r["d_coll_rel_err"] <= 1e-12 for r in strict if r["passes"])
    assert pytest.approx(0.2) == TOLERATED_BIN_REL_ERR, "1 - a_max / a_brake = 1 - 8/10"
