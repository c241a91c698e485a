"""Full-size presets, executed: two real training steps per preset (batch 1 unless asked), against the
planner.

Each preset runs in a process of its own (``--run``), built with random weights (no download) as
``capvector fit`` builds it: frozen weights in bf16 (``model.frozen_dtype``, built so:
``backbones.materialize``), LoRA r 32 alpha 16 (OpenVLA-OFT's recipe; Pi0.5's recipe trains every
weight, which no 24 GiB host holds: its full fine-tuning figure is the planner's), ``bf16-mixed``,
through ``VLAModule`` and Lightning's loop with the recipe's ``StepCost`` callback (its
``ExportOnFitEnd`` is left out: a full-size export is 7-15 GB of disk per run). Text goes through
a byte-level tokenizer standing in for the real one (the family's tiny preset's, as the planner
uses: ``stand_in_tokenizer``), at the preset's real vocabulary size (the embedding and LM head
keep their full shape); no real tokenizer can be had offline here.

Recorded per preset and variant: the two losses (finite), which parameters received gradients
(LoRA and heads only), the seconds of the second step, the peak RSS above the process's RSS once
everything is imported (``resource.getrusage`` high-water mark; torch has no CPU allocator
statistics, so RSS stands in for the allocator's peak) and the planner's CPU estimate for the same
settings (``estimate_memory(..., device="cpu")``, math attention as the CPU runs it).

Results go to ``--out`` (JSON, rewritten atomically after each preset); a preset already there is
skipped, so an interrupted run resumes preset by preset.

    python benchmarks/bench_full_size.py --presets pi05-3b [--variants sft aux ...] [--out FILE]
        [--vector DIR] [--export DIR] [--threads N] [--steps N]
    python benchmarks/bench_full_size.py --table docs/results/full_size.json ...  # the summary
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

FULL_SIZE = [
    "openvla-oft-7b", "openvla-oft-aloha-7b", "pi05-3b",
    "starvla-qwen2.5-vl-3b-oft", "starvla-qwen2.5-vl-3b-gr00t", "starvla-qwen2.5-vl-3b-layerwise",
    "starvla-qwen3-vl-4b-oft", "starvla-qwen3-vl-4b-gr00t", "starvla-qwen3-vl-4b-layerwise",
]  # fmt: skip
VARIANTS = ("sft", "sft+ckpt", "aux", "aux+ckpt", "capvector", "capvector+ckpt")
"""Plain SFT; aux-SFT with both objectives (``configs/recipes/aux_sft.yaml``'s spatial alignment
and reasoning co-training); CapVector (``MergeCapabilityVector`` at fit start and
``OrthogonalRegularization`` in LoRA mode, from ``--vector``); each with (``+ckpt``) and without
activation checkpointing."""
GIB = 1024**3
ROOT = Path(__file__).resolve().parents[1]


def high_water() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def callbacks_of(variant: str, vector: str | None, float32_weights: bool = True) -> list[Any]:
    """The recipe's callbacks of ``variant`` beyond plain SFT's ``StepCost``."""
    from capvector.callbacks import (
        AuxiliaryObjective,
        MergeCapabilityVector,
        OrthogonalRegularization,
    )
    from capvector.objectives import GeometricTeacher, ReasoningCoTraining, SpatialAlignment

    kind = variant.removesuffix("+ckpt")
    if kind == "aux":  # configs/recipes/aux_sft.yaml's two objectives, its weights
        teacher = GeometricTeacher(feature_dim=64, position_embedding=True)
        return [
            AuxiliaryObjective(SpatialAlignment(teacher=teacher, weight=0.5)),
            AuxiliaryObjective(ReasoningCoTraining(weight=0.1)),
        ]
    if kind == "capvector":
        if vector is None:
            raise SystemExit("the capvector variants need --vector DIR (a vector of this preset)")
        return [
            MergeCapabilityVector(vector, float32_weights=float32_weights),
            OrthogonalRegularization(vector, mode="lora"),
        ]
    return []


def run_one(
    preset: str,
    variant: str,
    vector: str | None = None,
    export: str | None = None,
    lr: float | None = None,
    steps: int = 2,
    strategy: str = "auto",
    devices: int = 1,
    overrides: dict[str, Any] | None = None,
    batch_size: int = 1,
    float32_weights: bool = True,
) -> dict[str, Any] | None:
    """Two steps of ``preset`` in this process; the row for the JSON. With ``export``, the model is
    exported there afterwards (in the base's dtype, as ``ExportOnFitEnd`` writes it). ``lr``
    replaces the family's learning rate: two steps at Pi0.5's 2.5e-5 move LoRA-merged weights by
    less than a bf16 step, so two bf16 exports would be identical and no vector could be taken.
    ``steps=0`` builds and exports only (a full-size export to serve, with less memory than a
    step needs). ``strategy`` (``ddp`` or ``fsdp2``: ``ModelParallelStrategy``, as
    ``configs/scale/fsdp2.yaml``) over ``devices`` CPU processes, each rank's peak gathered: rank 0
    returns the row, the others None. ``overrides`` change the preset's config (a mid-size model)."""
    import lightning as L
    import torch

    from capvector.callbacks import StepCost
    from capvector.data.datamodule import RobotDataModule
    from capvector.module import VLAModule
    from capvector.profiling.memory import stand_in_tokenizer
    from capvector.profiling.meta import import_build_dependencies
    from capvector.training.lora import LoraSettings

    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import write_demo_file

    checkpointing = variant.endswith("+ckpt")
    import_build_dependencies()

    class Record(L.Callback):
        def __init__(self) -> None:
            self.losses: list[float] = []
            self.seconds: list[float] = []
            self.with_grad: set[str] = set()

        def on_train_batch_start(self, *args: Any) -> None:
            self._start = time.perf_counter()

        def on_after_backward(self, trainer: L.Trainer, module: L.LightningModule) -> None:
            self.with_grad |= {n for n, p in module.named_parameters() if p.grad is not None}

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
            self.seconds.append(time.perf_counter() - self._start)
            self.losses.append(float(outputs["loss"]))

    with tempfile.TemporaryDirectory() as tmp:
        demos = write_demo_file(Path(tmp) / "demos.hdf5", lengths=(12,), image_size=224)
        torch.manual_seed(0)
        aux = variant.startswith("aux")
        dm = RobotDataModule(
            train_files=[str(demos)], batch_size=batch_size, augment=False, load_depth=aux,
            load_annotations=aux,
        )  # fmt: skip
        baseline = high_water()
        start = time.perf_counter()
        module = VLAModule(
            backbone=preset, backbone_overrides={**stand_in_tokenizer(preset), **(overrides or {})},
            data_spec=dm.spec,
            lora=LoraSettings(r=32, alpha=16), frozen_dtype="bfloat16",
            activation_checkpointing=checkpointing,
        )  # fmt: skip
        build_seconds = time.perf_counter() - start
        if lr is not None:
            module.optimizer_settings = dataclasses.replace(module.optimizer_settings, lr=lr)
        built_peak = high_water() - baseline
        record = Record()
        trainer = L.Trainer(
            max_steps=steps, accelerator="cpu", precision="bf16-mixed", logger=False,
            enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
            enable_checkpointing=False, default_root_dir=tmp,
            callbacks=[StepCost(), *callbacks_of(variant, vector, float32_weights), record],
            gradient_clip_val=None if strategy == "fsdp2" else 1.0,  # FSDP2 clips by norm only
            strategy=strategy_of(strategy, devices), devices=devices,
        )  # fmt: skip
        if steps:
            trainer.fit(module, dm)
    peak = high_water() - baseline
    # Each rank's (peak above its baseline, its peak RSS): the baselines differ (rank 0 launched
    # the others after building its model).
    rank_peaks = [(peak, high_water())]
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        rank_peaks = [(0, 0)] * torch.distributed.get_world_size()
        torch.distributed.all_gather_object(rank_peaks, (peak, high_water()))
        if torch.distributed.get_rank() != 0:
            return None
    exported: dict[str, Any] = {}
    if export is not None:
        start = time.perf_counter()
        module.export(export, overwrite=True)
        exported = {
            "export": export,
            "export_seconds": time.perf_counter() - start,
            "export_bytes": sum(f.stat().st_size for f in Path(export).iterdir()),
            "export_peak_rss_above_baseline_gib": (high_water() - baseline) / GIB,
        }
    params = dict(module.named_parameters())
    trainable = {n for n, p in params.items() if p.requires_grad}
    unexpected = sorted(
        n for n in record.with_grad if ".lora_" not in n and n not in trainable
    )  # fmt: skip
    stored = sum(p.numel() * p.element_size() for p in params.values())
    return {
        "preset": preset,
        "variant": variant,
        "batch_size": batch_size,
        "parameters": sum(p.numel() for p in params.values()),
        "stored_gib": stored / GIB,
        "losses": record.losses,
        "finite": all(math.isfinite(x) for x in record.losses),
        "with_grad": len(record.with_grad),
        "with_grad_lora": sum(".lora_" in n for n in record.with_grad),
        "with_grad_other": sorted(
            {n.split(".lora_")[0] for n in record.with_grad if ".lora_" not in n}
        ),
        "grad_outside_trainable": unexpected,
        "build_seconds": build_seconds,
        "step_seconds": record.seconds,
        "peak_rss_above_baseline_gib": peak / GIB,
        **({"strategy": strategy, "devices": devices} if devices > 1 else {}),
        **(
            {
                "rank_peak_rss_above_baseline_gib": [above / GIB for above, _ in rank_peaks],
                "rank_peak_rss_gib": [rss / GIB for _, rss in rank_peaks],
            }
            if devices > 1
            else {}
        ),
        **({"overrides": overrides} if overrides else {}),
        "build_peak_rss_above_baseline_gib": built_peak / GIB,
        "objectives": sorted(module.objectives),
        "lr": module.optimizer_settings.lr,
        "vector": vector,
        **({"float32_weights": float32_weights} if vector else {}),
        **exported,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
    }


def strategy_of(name: str, devices: int) -> Any:
    """Lightning's strategy for ``name``: ``fsdp2`` as ``configs/scale/fsdp2.yaml`` sets it."""
    if name != "fsdp2":
        return name
    from lightning.pytorch.strategies import ModelParallelStrategy

    return ModelParallelStrategy(
        data_parallel_size=devices, tensor_parallel_size=1, save_distributed_checkpoint=False
    )


def plan(
    preset: str,
    variant: str,
    batch_size: int = 1,
    vector: str | None = None,
    float32_weights: bool = True,
) -> dict[str, Any]:
    """The planner's CPU estimate for ``run_one``'s settings. In a process of its own, after the
    run's: its meta trace takes minutes at full size, and the run's memory is gone by then."""
    from capvector.profiling.memory import estimate_memory
    from capvector.profiling.settings import TrainingSettings

    checkpointing = variant.endswith("+ckpt")
    settings = TrainingSettings(
        batch=batch_size, precision="bf16-mixed", strategy="ddp", lora_rank=32, frozen_dtype="bfloat16",
        attention="math", activation_checkpointing=checkpointing,
        objectives=("spatial", "reasoning") if variant.startswith("aux") else (),
        vector=vector if variant.startswith("capvector") else None,
        vector_float32_weights=float32_weights,
    )  # fmt: skip
    planned = estimate_memory(preset, settings, device="cpu")
    activations = planned.activations_checkpointed if checkpointing else planned.activations
    working = planned.working_checkpointed if checkpointing else planned.working
    terms = {
        "parameters": planned.parameters, "gradients": planned.gradients,
        "optimizer": planned.optimizer, "activations": activations, "working": working,
        "objectives": planned.objectives_checkpointed if checkpointing else planned.objectives,
        "vector": planned.vector,
    }  # fmt: skip
    return {
        "planner_cpu_gib": planned.total / GIB,
        "planner_cpu_terms_gib": {k: v / GIB for k, v in terms.items()},
    }


def write_rows(rows: list[dict[str, Any]], out: Path) -> None:
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(rows, indent=2) + "\n")
    tmp.replace(out)


def table(files: list[Path]) -> str:
    """One markdown row per single-process run in ``files`` (``--out`` JSONs), preset by preset:
    the summary docs/performance.md shows."""
    rows = [r for f in files for r in json.loads(f.read_text()) if "devices" not in r]
    rows.sort(key=lambda r: (FULL_SIZE.index(r["preset"]), r.get("batch_size") or 1,
                             VARIANTS.index(r["variant"])))  # fmt: skip
    lines = [
        "| preset | variant | batch | losses | step s | peak above baseline | planner (CPU) "
        "| measured / planned | threads | lr |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        planned = r.get("planner_cpu_gib")
        peak = r["peak_rss_above_baseline_gib"]
        bf16_merge = " (c merged into bf16)" if r.get("float32_weights") is False else ""
        lines.append(
            f"| `{r['preset']}` | `{r['variant']}`{bf16_merge} | {r.get('batch_size') or 1} "
            f"| {', '.join(f'{x:.3f}' for x in r['losses'])} "
            f"| {', '.join(f'{x:.0f}' for x in r['step_seconds'])} | {peak:.2f} GiB "
            f"| {f'{planned:.2f} GiB' if planned else '—'} "
            f"| {f'{peak / planned:.2f}' if planned else '—'} | {r['threads']} | {r['lr']:g} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=FULL_SIZE)
    parser.add_argument("--variants", nargs="+", default=["sft"], choices=VARIANTS)
    parser.add_argument("--out", type=Path, default=ROOT / "docs/results/full_size.json")
    parser.add_argument("--vector", help="vector folder of the preset (capvector variants)")
    parser.add_argument("--export", type=Path, help="export each run to EXPORT/PRESET-VARIANT")
    parser.add_argument("--threads", type=int, default=2, help="OMP_NUM_THREADS of each run")
    parser.add_argument("--lr", type=float, help="learning rate (default: the family's)")
    parser.add_argument("--steps", type=int, default=2, help="training steps (0: build, export)")
    parser.add_argument("--strategy", default="auto", choices=("auto", "ddp", "fsdp2"))
    parser.add_argument("--devices", type=int, default=1, help="CPU processes (with --strategy)")
    parser.add_argument("--overrides", type=json.loads, help="preset config changes (JSON)")
    parser.add_argument("--batch-size", type=int, default=1, help="per-process batch")
    parser.add_argument(
        "--float32-weights", action=argparse.BooleanOptionalAction, default=True,
        help="capvector variants: keep the weights c changes in float32 (MergeCapabilityVector's)",
    )  # fmt: skip
    parser.add_argument("--table", nargs="+", type=Path, help="print these JSONs' summary table")
    parser.add_argument(
        "--replan", action="store_true",
        help="only recompute the planner's figures of --out's rows of --presets and --variants",
    )  # fmt: skip
    parser.add_argument("--run", nargs=2, metavar=("PRESET", "VARIANT"), help=argparse.SUPPRESS)
    parser.add_argument("--plan", nargs=2, metavar=("PRESET", "VARIANT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.table:
        print(table(args.table))
        return
    if args.plan:
        print(json.dumps(plan(*args.plan, args.batch_size, args.vector, args.float32_weights)))
        return
    if args.run:
        export = None if args.export is None else str(args.export / "-".join(args.run))
        row = run_one(
            *args.run, vector=args.vector, export=export, lr=args.lr, steps=args.steps,
            strategy=args.strategy, devices=args.devices, overrides=args.overrides,
            batch_size=args.batch_size, float32_weights=args.float32_weights,
        )  # fmt: skip
        if row is not None:  # rank 0
            print(json.dumps(row))
        return
    rows: list[dict[str, Any]] = json.loads(args.out.read_text()) if args.out.is_file() else []
    if args.replan:
        for row in rows:
            if (
                row["preset"] in args.presets
                and row["variant"] in args.variants
                and "devices" not in row
            ):
                row.update(plan(
                    row["preset"], row["variant"], row.get("batch_size") or 1, row.get("vector"),
                    row.get("float32_weights", True),
                ))  # fmt: skip
                write_rows(rows, args.out)
        return
    done = {(r["preset"], r["variant"], r.get("batch_size", 1)) for r in rows}
    for preset in args.presets:
        for variant in args.variants:
            if (preset, variant, args.batch_size) in done:
                print(f"{preset} {variant} batch {args.batch_size}: in {args.out}, skipped")
                continue
            extra = [*(["--vector", args.vector] if args.vector else [])]
            extra += ["--export", str(args.export)] if args.export else []
            extra += ["--lr", str(args.lr)] if args.lr is not None else []
            extra += ["--steps", str(args.steps)] if args.steps != 2 else []
            if args.devices > 1:
                extra += ["--strategy", args.strategy, "--devices", str(args.devices)]
            extra += ["--overrides", json.dumps(args.overrides)] if args.overrides else []
            extra += ["--batch-size", str(args.batch_size)] if args.batch_size != 1 else []
            extra += [] if args.float32_weights else ["--no-float32-weights"]
            out = subprocess.run(
                [sys.executable, __file__, "--run", preset, variant, *extra],
                capture_output=True, text=True,
                env={**os.environ, "OMP_NUM_THREADS": str(args.threads)},
            )  # fmt: skip
            if out.returncode != 0:
                print(f"{preset} {variant}: failed (exit {out.returncode})\n{out.stderr[-3000:]}")
                continue
            row = json.loads(out.stdout.strip().splitlines()[-1])
            # The planner plans the preset itself, on one device: no figure for the others.
            if not args.overrides and args.devices == 1 and args.steps:
                planned = subprocess.run(
                    [sys.executable, __file__, "--plan", preset, variant, *extra],
                    capture_output=True,
                    text=True, env={**os.environ, "OMP_NUM_THREADS": str(args.threads)},
                )  # fmt: skip
                if planned.returncode == 0:
                    row.update(json.loads(planned.stdout.strip().splitlines()[-1]))
                else:  # the measured row is kept; what the planner said instead of its figure
                    row["planner_error"] = planned.stderr.strip().splitlines()[-1]
            row["command"] = " ".join(
                ["python benchmarks/bench_full_size.py --presets", preset, "--variants", variant,
                 *extra, "--threads", str(args.threads)]
            )  # fmt: skip
            rows.append(row)
            write_rows(rows, args.out)
            print(json.dumps(row))


if __name__ == "__main__":
    main()
