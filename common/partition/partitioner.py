"""One split, from the model file to the split directory, one private step per stage.

In the manner of ``onnx.utils.Extractor``: load and check the model, fix its input shapes, probe
every tensor's dtype and shape, collect the candidate cuts, write the weights once and the
sub-models (checked with ``onnx.checker``), verify them with the runtime the caller gives, then
number the usable cuts; with ``segments``, write and verify the segment between every two of
them (``common.partition.segments``); write the manifest. The stages themselves live in the
modules named for them; this class orders them and owns the output directory.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx

from common.errors import UserError
from common.models import ZOO_PREFIX, ModelRef
from common.partition.builder import SubModelBuilder
from common.partition.candidates import Candidate, CutCollector
from common.partition.errors import OptionError, one_line
from common.partition.graph import DataflowGraph
from common.partition.loading import input_specs, load_onnx, normalize
from common.partition.manifest import (
    FULL_NAME,
    MANIFEST_NAME,
    WEIGHTS_NAME,
    Cut,
    Partition,
    TensorSpec,
    excluded_cut,
)
from common.partition.options import InputShape, check_max_cut_tensors, cuts_option
from common.partition.probe import probe_specs
from common.partition.segments import SegmentWriter
from common.partition.sharing import shareable_initializers
from common.partition.verify import RunnerFactory, sample_feeds, verify_cuts, verify_segments
from common.partition.weights import WeightStore, save_graph, with_external


class Partitioner:
    """One split: the stages from loading the model to the manifest, one private step each.

    ``runner`` builds the runtime that verification runs the cuts with; it is only called when
    ``verify`` is true. ``segments`` also writes the segment between every two usable cuts.
    """

    def __init__(
        self,
        ref: ModelRef,
        cuts: str | Sequence[str],
        max_cut_tensors: int,
        input_shape: InputShape,
        verify: bool,
        atol: float,
        threads: int | None,
        prune: bool = True,
        *,
        runner: RunnerFactory,
        segments: bool = False,
    ) -> None:
        self.ref = ref
        self.segments = segments
        self.prune = prune
        self.cuts = cuts_option(cuts)
        check_max_cut_tensors(max_cut_tensors)
        self.max_cut_tensors = max_cut_tensors
        # A zoo model's input shape (C×H×W) chose the size it was exported at; the file's input
        # (the uint8 camera image, 1×H×W×C) is static, so nothing is left to fix.
        self.input_shape = None if ref.spec.startswith(ZOO_PREFIX) else input_shape
        self.verify = verify
        self.atol = atol
        self.threads = threads
        self.runner = runner
        self.excluded: list[Cut] = []

    def run(self, out_dir: Path) -> Partition:
        model = normalize(load_onnx(self.ref.path), self.input_shape)
        graph = DataflowGraph(model)
        feeds = sample_feeds(input_specs(model))
        specs = probe_specs(model, graph, feeds, spec=self.ref.spec, threads=self.threads)
        collector = CutCollector(self.cuts, self.max_cut_tensors, self.ref.spec)
        candidates = collector.collect(graph, specs)
        collector.measure(candidates, model, graph, specs)
        if self.cuts == "auto" and self.prune:
            candidates = collector.prune(candidates)
        self.excluded.extend(collector.excluded)
        self._prepare_dir(out_dir)
        external = WeightStore(out_dir / WEIGHTS_NAME).write(model, shareable_initializers(graph))
        save_graph(with_external(model, external), out_dir / FULL_NAME)
        builder = SubModelBuilder(model, graph, specs, external)
        for n, cand in enumerate(candidates):
            self._write_cut(builder, cand, out_dir, f"cand{n:03d}")
        usable = [c for c in candidates if not c.reason]
        if self.verify:
            self._verify(out_dir, graph, specs, usable, feeds)
        part = self._finish(out_dir, graph, specs, candidates)
        if self.segments:
            self._segments(part, builder, feeds)
        part.write_manifest()
        return part

    # -- stages --

    def _prepare_dir(self, out_dir: Path) -> None:
        if out_dir.exists() and not out_dir.is_dir():
            raise OptionError(
                "out_dir", "{option} {path} exists and is not a directory", path=out_dir
            )
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"cannot create {out_dir}: {exc.strerror}") from None
        # Files of an earlier split in the same directory would be stale; remove only ours.
        for pattern in ("cand*.onnx", "cut*.prefix.onnx", "cut*.suffix.onnx", "cut*.segment.onnx"):
            for old in out_dir.glob(pattern):
                old.unlink()
        for name in (MANIFEST_NAME, FULL_NAME, WEIGHTS_NAME):
            with contextlib.suppress(FileNotFoundError):
                (out_dir / name).unlink()

    def _write_cut(
        self, builder: SubModelBuilder, cand: Candidate, out_dir: Path, stem: str
    ) -> None:
        if cand.reason:
            return
        plan = cand.plan
        try:
            prefix_outputs = [t for t in plan.tensors if t not in builder.graph.input_set]
            if prefix_outputs:
                cand.prefix = out_dir / f"{stem}.prefix.onnx"
                prefix = builder.build(
                    f"{stem}_prefix", plan.prefix_nodes, plan.prefix_inputs, prefix_outputs
                )
                save_graph(prefix, cand.prefix)
                onnx.checker.check_model(str(cand.prefix))
            cand.suffix = out_dir / f"{stem}.suffix.onnx"
            suffix = builder.build(
                f"{stem}_suffix", plan.suffix_nodes, plan.tensors, builder.graph.outputs
            )
            save_graph(suffix, cand.suffix)
            onnx.checker.check_model(str(cand.suffix))
        except Exception as exc:
            cand.reason = f"onnx.checker rejected the sub-model: {one_line(exc)}"

    def _verify(
        self,
        out_dir: Path,
        graph: DataflowGraph,
        specs: Mapping[str, TensorSpec | None],
        usable: list[Candidate],
        feeds: dict[str, np.ndarray],
    ) -> None:
        """Compare every usable cut with the full model; a cut that differs gets the reason."""
        part = self._partition(out_dir, graph, specs, usable, verified=False)
        checks = verify_cuts(part, feeds, self.runner, atol=self.atol, threads=self.threads)
        for cand, check in zip(usable, checks, strict=True):
            cand.max_abs_err = check.max_abs_err
            cand.reason = check.failure

    def _segments(
        self, part: Partition, builder: SubModelBuilder, feeds: dict[str, np.ndarray]
    ) -> None:
        """Write the segment between every two cuts of ``part``, verify them, keep the good ones;
        the others are listed under ``excluded`` with the reason."""
        writer = SegmentWriter(builder, part.dir)
        part.segments = writer.write_all(part.cuts)
        part.excluded.extend(writer.excluded)
        if not self.verify or not part.segments:
            return
        checks = verify_segments(part, feeds, self.runner, atol=self.atol, threads=self.threads)
        kept = []
        for seg, check in zip(part.segments, checks, strict=True):
            if check.failure:
                seg.path.unlink(missing_ok=True)
                part.excluded.append(
                    excluded_cut(
                        part.cuts[seg.end].tensors,
                        f"segment from cut {seg.start} to cut {seg.end}: {check.failure}",
                    )
                )
                continue
            seg.verified, seg.max_abs_err = True, check.max_abs_err
            kept.append(seg)
        part.segments = kept

    def _finish(
        self,
        out_dir: Path,
        graph: DataflowGraph,
        specs: Mapping[str, TensorSpec | None],
        candidates: list[Candidate],
    ) -> Partition:
        """Number usable cuts 0..K-1, rename their files, drop the others."""
        usable: list[Candidate] = []
        for cand in candidates:
            if cand.reason:
                self.excluded.append(excluded_cut(cand.plan.tensors, cand.reason))
                for path in (cand.prefix, cand.suffix):
                    if path is not None:
                        path.unlink(missing_ok=True)
                continue
            k = len(usable)
            if cand.prefix is not None:
                cand.prefix = cand.prefix.rename(out_dir / f"cut{k:03d}.prefix.onnx")
            assert cand.suffix is not None
            cand.suffix = cand.suffix.rename(out_dir / f"cut{k:03d}.suffix.onnx")
            usable.append(cand)
        return self._partition(out_dir, graph, specs, usable, verified=self.verify)

    def _partition(
        self,
        out_dir: Path,
        graph: DataflowGraph,
        specs: Mapping[str, TensorSpec | None],
        cands: list[Candidate],
        verified: bool,
    ) -> Partition:
        names = list(graph.inputs) + list(graph.outputs)
        for cand in cands:
            names.extend(cand.plan.tensors)
        table: dict[str, TensorSpec] = {}
        for name in names:
            spec = specs.get(name)
            if spec is not None:
                table[name] = spec
        cuts = [
            Cut(
                index=k,
                tensors=list(c.plan.tensors),
                bytes=sum(table[t].nbytes for t in c.plan.tensors),
                prefix=c.prefix,
                suffix=c.suffix,
                verified=verified,
                max_abs_err=c.max_abs_err if verified else None,
                prefix_flops=c.prefix_flops,
                suffix_flops=c.suffix_flops,
            )
            for k, c in enumerate(cands)
        ]
        return Partition(
            dir=out_dir,
            model=self.ref.spec,
            digest=self.ref.digest,
            inputs=list(graph.inputs),
            outputs=list(graph.outputs),
            specs=table,
            cuts=cuts,
            excluded=list(self.excluded),
            options={
                "cuts": self.cuts,
                "max_cut_tensors": self.max_cut_tensors,
                "input_shapes": {n: list(table[n].shape) for n in graph.inputs if n in table},
                "verify": self.verify,
                "atol": self.atol,
                "prune": self.prune,
                # Only when on: the options of splits without segments stay as they were.
                **({"segments": True} if self.segments else {}),
            },
        )
