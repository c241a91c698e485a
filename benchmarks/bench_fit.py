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
reports each fit's step time (its ``perf/step_seconds``) with the fits' default threads and with
``OMP_NUM_THREADS=2`` (what torch takes on a 2-core machine when nothing divides the cores).
``--data-only [--depth]`` times loading batches alone (CPU time), as the recipe's fits load them
with ``--depth --batch 16``.
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
    from capvector.envs.robosuite.demos import record_demos

    record_demos("Lift", episodes, out, depth=True, progress=False)
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


def data_only(args: argparse.Namespace, data_file: Path, root: Path) -> None:
    """CPU time to load one training batch (as the recipe's fits read it with ``--depth``: depth
    and annotations too), the median over two epochs after the first batch."""
    torch.set_num_threads(args.threads)
    data = RobotDataModule(
        train_files=[str(data_file)], batch_size=args.batch, load_depth=args.depth,
        load_annotations=args.depth,
    )  # fmt: skip
    loader = data.train_dataloader()
    times = []
    for _ in range(2):
        batches = iter(loader)
        next(batches)
        while True:
            began = time.process_time()
            if next(batches, None) is None:
                break
            times.append(time.process_time() - began)
    what = "images, depth and annotations" if args.depth else "images"
    print(
        f"{statistics.median(times) * 1e3:.1f} ms of CPU per batch of {args.batch} ({what}), "
        f"median of {len(times)}"
    )


def side_by_side(args: argparse.Namespace, data_file: Path, root: Path) -> None:
    """Per-fit step time of two ``capvector fit`` started by hand at once: with their default
    threads (``ShareCores``: one each on 2 CPUs) and with two each."""

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

    arms = {"default (ShareCores)": None, "OMP_NUM_THREADS=2 (torch's default before)": "2"}
    per_fit: dict[str, list[float]] = {label: [] for label in arms}
    for r in range(args.rounds):  # the arms alternate, so the machine's other load hits both
        for i, (label, threads) in enumerate(arms.items()):
            per_fit[label] += run([f"a-{r}-{i}", f"b-{r}-{i}"], threads)
    print(
        f"{args.preset}, batch {args.batch}, two fits at once, {args.steps} steps each, "
        f"{args.rounds} round(s), {len(os.sched_getaffinity(0))} CPUs, load average "
        f"{os.getloadavg()[0]:.1f}\n"
    )
    baseline = statistics.median(per_fit[next(iter(arms))])
    print("| threads of each fit | ms/step per fit (median) | × default |")
    print("|---|---|---|")
    for label, seconds in per_fit.items():
        median = statistics.median(seconds)
        print(f"| {label} | {median * 1e3:.1f} | {median / baseline:.2f} |")


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
    parser.add_argument("--data-only", action="store_true", help="time loading batches alone")
    parser.add_argument("--depth", action="store_true", help="--data-only: depth + annotations")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        data_file = args.data or record(root / "lift.hdf5", args.episodes)
        run = side_by_side if args.side_by_side else data_only if args.data_only else in_process
        run(args, data_file, root)


if __name__ == "__main__":
    main()
