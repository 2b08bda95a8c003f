"""Split + verify public architectures nobody here wrote (torchvision's, built from code).

Opt-in: needs torchvision (pinned in the dev lock, not a runtime dependency). Each model is built
without weights (seeded default initialisation), exported at opset 17 with the TorchScript
exporter like the zoo, 1x3x224x224 float input, then split with the defaults of
``elasticfog model split`` (automatic cuts, at most 2 tensors, pruned, verified). One progress line
per model on stderr; a markdown table (the one in docs/partitioning.md) or ``--json`` on stdout.

    python benchmarks/public_archs.py [--models resnet18,convnext_tiny] [--all] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any

from experiments.report import fmt, md_table

# 1-2 minutes on two cores, one of each kind of graph: residual, depthwise, squeeze-excitation,
# fire modules, channel shuffle, dense concatenation, channels-last blocks, attention.
DEFAULT_MODELS = (
    "resnet18",
    "mobilenet_v3_small",
    "efficientnet_b0",
    "convnext_tiny",
    "regnet_y_400mf",
    "squeezenet1_0",
    "shufflenet_v2_x0_5",
    "densenet121",
    "vit_b_16",
)
# --all adds these (about 5 minutes in all): the other families, and bigger or windowed ones.
MORE_MODELS = (
    "alexnet",
    "vgg11",
    "resnet50",
    "mobilenet_v2",
    "mobilenet_v3_large",
    "mnasnet0_5",
    "googlenet",
    "inception_v3",
    "regnet_x_400mf",
    "efficientnet_v2_s",
    "swin_t",
    "maxvit_t",
)
INPUT_SHAPE = (1, 3, 224, 224)
OPSET = 17
SEED = 0
# torch.library definitions live as long as their Library object.
_LIBRARIES: list[Any] = []


def torchvision_models() -> ModuleType:
    """``torchvision.models``, also where torchvision's C extension cannot load.

    The torchvision wheel that pairs with the pinned torch 2.13.0+cpu is a CUDA build: its
    ``_C`` extension does not load next to a CPU torch, and ``import torchvision`` then fails in
    ``torchvision/_meta_registrations.py``, which registers fake kernels for ``torchvision::nms``
    and ``torchvision::qnms`` unconditionally ("operator torchvision::nms does not exist"). Only
    the model builders are used here and classification models never call those detection ops,
    so their schemas are defined without any kernel and the import is tried again. With an
    extension that loads (a CPU torchvision) the first import succeeds and nothing is defined.
    """
    import torch

    try:
        import torchvision.models as models
    except RuntimeError as exc:
        if "torchvision::" not in str(exc):
            raise
        for name in [m for m in sys.modules if m.split(".")[0] == "torchvision"]:
            del sys.modules[name]
        lib = torch.library.Library("torchvision", "DEF")
        for op in ("nms", "qnms"):
            lib.define(f"{op}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        _LIBRARIES.append(lib)
        import torchvision.models as models
    return models


def export(name: str, path: Path) -> dict[str, Any]:
    """Build ``name`` without weights (seeded) and export it to ``path``; its parameter count."""
    import torch

    models = torchvision_models()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(SEED)
        with warnings.catch_warnings():
            # googlenet/inception_v3 warn that their default init will change; the TorchScript
            # exporter warns that it is deprecated (the dynamo one needs onnxscript).
            warnings.simplefilter("ignore")
            network = models.get_model(name, weights=None).eval()
            torch.onnx.export(
                network,
                (torch.zeros(INPUT_SHAPE),),
                str(path),
                dynamo=False,
                opset_version=OPSET,
                input_names=["input"],
                output_names=["logits"],
                do_constant_folding=True,
            )
    return {"params": sum(p.numel() for p in network.parameters())}


def bench_model(name: str, work: Path) -> dict[str, Any]:
    """Export, then split and verify as ``elasticfog model split`` does; the figures of one row.

    A model that fails to export or to split is a result too: its row carries ``error``.
    """
    import onnx

    from common.partition import DOMINATED_PREFIX, split_model

    row: dict[str, Any] = {"model": name, "error": None}
    path = work / f"{name}.onnx"
    try:
        t0 = time.perf_counter()
        row["params_m"] = round(export(name, path)["params"] / 1e6, 2)
        row["export_s"] = round(time.perf_counter() - t0, 2)
        row["nodes"] = len(onnx.load(str(path), load_external_data=False).graph.node)
        t0 = time.perf_counter()
        part = split_model(path, work / f"{name}.split")
        row["split_verify_s"] = round(time.perf_counter() - t0, 2)
    except Exception as exc:
        row["error"] = " ".join(str(exc).split())[:300] or type(exc).__name__
        return row
    failed = [e for e in part.excluded if not e.reason.startswith(DOMINATED_PREFIX)]
    row.update(
        cuts_found=len(part.cuts) + len(failed),
        cuts_verified=sum(c.verified for c in part.cuts),
        failures=[f"{'+'.join(e.tensors) or '-'}: {e.reason}" for e in failed],
        dominated=len(part.excluded) - len(failed),
        max_abs_err=max((c.max_abs_err or 0.0) for c in part.cuts),
        weights_mb=round((work / f"{name}.split" / "weights.bin").stat().st_size / 1e6, 2),
        inline_kib=round(inline_bytes(work / f"{name}.split" / "full.onnx") / 1024, 1),
    )
    return row


def inline_bytes(full: Path) -> int:
    """Bytes of the big constants kept out of weights.bin (not weight operands): each model
    file that uses one repeats it, and each session holds its own copy."""
    import onnx
    from onnx import numpy_helper

    from common.partition import EXTERNAL_MIN_BYTES

    model = onnx.load(str(full), load_external_data=False)
    sizes = [
        numpy_helper.to_array(t).nbytes
        for t in model.graph.initializer
        if t.data_location != onnx.TensorProto.EXTERNAL
    ]
    return sum(n for n in sizes if n >= EXTERNAL_MIN_BYTES)


def ok(row: dict[str, Any]) -> bool:
    """Split, and every cut found verified."""
    return row["error"] is None and row["cuts_verified"] == row["cuts_found"]


def markdown(rows: list[dict[str, Any]]) -> str:
    cols = [
        ("model", "model"),
        ("params_m", "params M"),
        ("nodes", "nodes"),
        ("cuts_found", "cuts found"),
        ("cuts_verified", "cuts verified"),
        ("dominated", "dominated (left out)"),
        ("max_abs_err", "max abs err"),
        ("weights_mb", "weights.bin MB"),
        ("inline_kib", "big constants inline KiB"),
        ("export_s", "export s"),
        ("split_verify_s", "split+verify s"),
    ]
    body = []
    for row in rows:
        cells = {key: row.get(key, "-") for key, _ in cols}
        if row["error"] is not None:
            cells["cuts_found"] = f"failed: {row['error']}"
        body.append([_cell(key, value) for key, value in cells.items()])
    return md_table([title for _, title in cols], body)


def _cell(key: str, value: Any) -> str:
    if not isinstance(value, float):
        return str(value)
    return {"max_abs_err": f"{value:.1g}", "inline_kib": f"{value:.1f}"}.get(key, fmt(value, 2))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", help=f"comma-separated (default: {','.join(DEFAULT_MODELS)})")
    parser.add_argument(
        "--all", action="store_true", help="the default set and " + ", ".join(MORE_MODELS)
    )
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args()
    if args.models:
        names = [m.strip() for m in args.models.split(",") if m.strip()]
    else:
        names = list(DEFAULT_MODELS) + (list(MORE_MODELS) if args.all else [])
    models = torchvision_models()
    known = set(models.list_models(module=models))
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(f"unknown torchvision model(s): {', '.join(unknown)}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # A fresh cache: nothing is reused from an earlier run.
        os.environ["ELASTICFOG_CACHE_DIR"] = str(Path(tmp) / "cache")
        for n, name in enumerate(names, 1):
            work = Path(tmp) / name
            work.mkdir()
            row = bench_model(name, work)
            rows.append(row)
            if row["error"] is None:
                status = (
                    f"{row['nodes']} nodes, export {row['export_s']:.1f} s, split+verify "
                    f"{row['split_verify_s']:.1f} s, "
                    f"{row['cuts_verified']}/{row['cuts_found']} cuts verified"
                )
            else:
                status = f"FAILED: {row['error']}"
            print(f"[{n}/{len(names)}] {name}: {status}", file=sys.stderr, flush=True)
            for failure in row.get("failures", []):
                print(f"    failed {failure}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print(f"host: {platform.machine()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}")
        print(markdown(rows))
    return 0 if all(ok(row) for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
