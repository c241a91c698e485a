"""A ``capvector fit`` step against a bare PyTorch loop of the same model on the same batch.

The fit arm is Lightning's loop as ``capvector fit`` runs it (``RobotDataModule`` over recorded
robosuite demos, training augmentation on, the CSV logger, the progress bar, ``StepCost``): its step
is the wall time from one batch's start to the next one's, so data loading, augmentation, logging
and the loop's own work count. The bare arm is ``loss.backward(); optimizer.step()`` on one batch
collated once, the floor a step cannot go below. Both run in this process, interleaved (each round
runs some fit steps, then as many bare steps), so machine load hits both alike; the ratio is the
median over rounds. The fit arm also checks ``perf/step_seconds`` against wall-clock steps (the
fit's training time over its steps).

    python benchmarks/bench_fit.py [--preset openvla-oft-tiny] [--rounds 7] [--steps 20]

``--side-by-side`` instead starts ``capvector fit`` twice at once (as two users would, by hand) and
reports each fit's step time against one fit alone, with the fits' default threads and with
``OMP_NUM_THREADS=2`` (what torch takes on a 2-core machine when nothing divides the cores).
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch

from capvector.callbacks import StepCost
from capvector.data.datamodule import RobotDataModule, noise_seeds
from capvector.module import VLAModule


class WallClock(L.Callback):
    """Wall and process CPU time of the training loop from its first batch's start to its end: the
    steady state of a longer fit (each step also fetches a batch ahead, as the first one did before
    the clock started)."""

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.first_step = trainer.global_step

    def on_train_batch_start(self, trainer: L.Trainer, *args: Any) -> None:
        if trainer.global_step == self.first_step:
            self.began = time.perf_counter(), time.process_time()

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.wall = time.perf_counter() - self.began[0]
        self.cpu = time.process_time() - self.began[1]


def record(out: Path, episodes: int) -> Path:
    from capvector.sim.demos import record_demos

    record_demos("Lift", episodes, out, depth=False, progress=False)
    return out


def fit_steps(
    module: VLAModule, data: RobotDataModule, steps: int, root: Path
) -> tuple[float, float, float]:
    """(wall seconds, CPU seconds per step, the fit's last ``perf/step_seconds``) over ``steps``
    fit steps."""
    from capvector.training.loggers import CSVLogger

    clock = WallClock()
    trainer = L.Trainer(
        max_steps=steps, accelerator="cpu", devices=1, logger=CSVLogger(root, name="fit"),
        log_every_n_steps=steps, callbacks=[StepCost(), clock], enable_checkpointing=False,
        enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
        default_root_dir=root,
    )  # fmt: skip
    trainer.fit(module, data)
    logged = float(trainer.callback_metrics["perf/step_seconds"])
    return clock.wall / steps, clock.cpu / steps, logged


def bare_steps(
    module: VLAModule, optimizer: torch.optim.Optimizer, batch: dict, steps: int
) -> tuple[float, float]:
    """(wall seconds, CPU seconds) per step of the plain loop on one batch."""
    began = time.perf_counter(), time.process_time()
    for _ in range(steps):
        losses = module.compute_losses(batch)
        optimizer.zero_grad(set_to_none=True)
        losses["action"].backward()
        optimizer.step()
    return (time.perf_counter() - began[0]) / steps, (time.process_time() - began[1]) / steps


def in_process(args: argparse.Namespace, data_file: Path, root: Path) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    data = RobotDataModule(train_files=[str(data_file)], batch_size=args.batch)
    module = VLAModule(backbone=args.preset, data_spec=data.spec)
    batch: dict[str, Any] = next(iter(data.train_dataloader()))
    batch["noise_seed"] = noise_seeds(batch["index"], 0, seed=0)  # as the fit's batches carry
    optimizer = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=1e-4)
    bare_steps(module, optimizer, batch, 3)  # warm-up (allocator, lazy init)
    fit_steps(module, data, 3, root / "warmup")
    fit, bare, reported = [], [], []
    for r in range(args.rounds):
        *fit_times, logged = fit_steps(module, data, args.steps, root / f"round{r}")
        fit.append(fit_times)
        reported.append(logged / fit_times[0])
        bare.append(bare_steps(module, optimizer, batch, args.steps))
    print(
        f"{args.preset}, batch {args.batch}, {args.rounds} interleaved rounds of {args.steps} "
        f"steps, {args.threads} thread(s), {len(os.sched_getaffinity(0))} CPUs, load average "
        f"{os.getloadavg()[0]:.1f}\n"
    )
    print("| arm | wall ms/step | × bare loop | CPU ms/step | × bare loop |")
    print("|---|---|---|---|---|")
    for name, times in (("bare PyTorch loop, one batch", bare), ("capvector fit", fit)):
        cells = []
        for kind in (0, 1):
            ratio = statistics.median(t[kind] / b[kind] for t, b in zip(times, bare, strict=True))
            cells += [f"{statistics.median(t[kind] for t in times) * 1e3:.1f}", f"{ratio:.3f}"]
        print(f"| {name} | {' | '.join(cells)} |")
    walls = [f[0] / b[0] for f, b in zip(fit, bare, strict=True)]
    print(f"\nwall ratios per round: {', '.join(f'{r:.3f}' for r in walls)}")
    print(
        "perf/step_seconds / wall-clock step, per round: "
        f"{', '.join(f'{r:.3f}' for r in reported)} (median {statistics.median(reported):.3f})"
    )


def side_by_side(args: argparse.Namespace, data_file: Path, root: Path) -> None:
    """Per-fit step time of two hand-started ``capvector fit`` beside each other, against one."""

    def launch(name: str, threads: str | None) -> subprocess.Popen:
        env = {
            k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
        }
        if threads is not None:
            env["OMP_NUM_THREADS"] = threads
        command = [
            sys.executable, "-m", "capvector.cli", "fit", "--model.backbone", args.preset,
            f"--data.train_files=[{data_file}]", "--data.batch_size", str(args.batch),
            "--trainer.max_steps", str(args.steps), "--trainer.log_every_n_steps", "5",
            "--trainer.enable_progress_bar", "false", "--trainer.enable_checkpointing", "false",
            "--trainer.callbacks+=capvector.callbacks.StepCost",
            "--trainer.default_root_dir", str(root / name),
        ]  # fmt: skip
        return subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def step_seconds(name: str) -> float:
        (metrics,) = (root / name).rglob("metrics.csv")
        with open(metrics) as f:
            values = [
                float(r["perf/step_seconds"])
                for r in csv.DictReader(f)
                if r.get("perf/step_seconds")
            ]
        return statistics.median(values[1:])  # the first window holds the warm-up

    def run(names: list[str], threads: str | None) -> list[float]:
        processes = [launch(name, threads) for name in names]
        for process in processes:
            _, err = process.communicate()
            if process.returncode:
                raise SystemExit(err.decode()[-2000:])
        return [step_seconds(name) for name in names]

    rows = []
    for r in range(args.rounds):
        for threads in (None, "2"):
            label = "default threads" if threads is None else "OMP_NUM_THREADS=2"
            (alone,) = run([f"alone-{r}-{threads}"], threads)
            pair = run([f"a-{r}-{threads}", f"b-{r}-{threads}"], threads)
            rows.append((label, alone, pair))
    print(
        f"{args.preset}, batch {args.batch}, {args.steps} steps per fit, {args.rounds} round(s)\n"
    )
    print("| threads | one fit alone (ms/step) | two fits at once (ms/step, each) | × alone |")
    print("|---|---|---|---|")
    for label in ("default threads", "OMP_NUM_THREADS=2"):
        alone = statistics.median(a for lab, a, _ in rows if lab == label)
        pair = statistics.median(s for lab, _, p in rows if lab == label for s in p)
        print(f"| {label} | {alone * 1e3:.1f} | {pair * 1e3:.1f} | {pair / alone:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="openvla-oft-tiny")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--episodes", type=int, default=10, help="Lift demos to record")
    parser.add_argument("--data", type=Path, help="an HDF5 demo file instead of recording one")
    parser.add_argument("--side-by-side", action="store_true")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        data_file = args.data or record(root / "lift.hdf5", args.episodes)
        (side_by_side if args.side_by_side else in_process)(args, data_file, root)


if __name__ == "__main__":
    main()
