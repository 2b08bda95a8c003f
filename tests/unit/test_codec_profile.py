"""Which measured (cut, codec) entries become actions under a fidelity bound."""

from __future__ import annotations

from typing import Any

from common.codec_profile import Fidelity, select_codecs


def entry(name: str, size: float, *, top1: float | None = None, err: float = 0.0) -> dict[str, Any]:
    lossy = name.startswith(("jpeg", "int8", "fp16"))
    return {"name": name, "bytes": size, "top1_agreement": top1, "rel_err": err, "lossy": lossy}


ENTRIES = [
    entry("raw", 230_400),
    entry("raw+zstd", 220_000),  # saves under 10%: not worth its CPU
    entry("png", 90_000),
    entry("jpeg95", 16_000, top1=1.0),
    entry("jpeg80", 7_000, top1=1.0),
    entry("jpeg50", 4_500, top1=0.9),  # changes the answer on one frame in ten
]


def names(chosen: list[dict[str, Any]]) -> list[str]:
    return [e["name"] for e in chosen]


def test_raw_lossless_savings_and_the_lowest_jpeg_that_keeps_the_answers() -> None:
    assert names(select_codecs(ENTRIES, Fidelity())) == ["raw", "jpeg80", "png"]


def test_a_codec_a_baseline_names_is_kept_whatever_the_bound() -> None:
    chosen = names(select_codecs(ENTRIES, Fidelity(), required=["jpeg50"]))
    assert chosen[:2] == ["raw", "jpeg50"]


def test_a_bound_that_cannot_be_checked_admits_no_lossy_codec() -> None:
    assert not Fidelity().admits(None, 0.001)
    assert Fidelity(max_output_rel_err=0.01).admits(None, 0.001)
    assert not Fidelity(max_output_rel_err=0.01).admits(1.0, 0.02)
