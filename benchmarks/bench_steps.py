"""Training-step cost of each recipe arm on a tiny preset, measured in one run against plain SFT.

Arms: plain SFT, twice (the second copy's ratio is the measurement's own noise); SFT + orthogonal
regularization (the downstream CapVector step); aux-SFT with spatial alignment, with reasoning
co-training, and with both (the costs the capability vector is meant to remove). Time is the median
over interleaved rounds (each round times every arm once, so machine load hits all arms alike);
memory is the bytes autograd saves for the backward pass.

    python benchmarks/bench_steps.py [--preset openvla-oft-tiny] [--steps 30] [--batch 8]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from capvector.data.hdf5 import HDF5RobotDataset
from capvector.module import VLAModule
from capvector.objectives import ReasoningCoTraining, SpatialAlignment
from capvector.objectives.orthogonality import OrthogonalityLoss
from capvector.profiling.memory import saved_activation_bytes
from capvector.vectors import extract


def make_data(root: Path) -> Path:
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import write_demo_file

    return write_demo_file(root / "demos.hdf5", lengths=(40, 40))


def build_arms(
    preset: str, data: Path, root: Path
) -> dict[str, tuple[VLAModule, torch.optim.Optimizer]]:
    from capvector.data.datamodule import RobotDataModule

    spec = RobotDataModule(train_files=[str(data)], load_depth=True, load_annotations=True).spec
    base = VLAModule(backbone=preset, data_spec=spec)
    base.export(root / "pre")
    donor = VLAModule(pretrained=str(root / "pre"), data_spec=spec)
    with torch.no_grad():
        for p in donor.backbone.parameters():
            p.add_(torch.randn_like(p) * 1e-3)
    donor.export(root / "donor")
    extract(aux=root / "donor", sft=root / "pre", out=root / "vector")

    def module(*objectives: object) -> tuple[VLAModule, torch.optim.Optimizer]:
        m = VLAModule(pretrained=str(root / "pre"), data_spec=spec)
        for objective in objectives:
            objective.bind(m.backbone)  # type: ignore[attr-defined]
            m.add_objective(objective)  # type: ignore[arg-type]
        return m, torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], lr=1e-4)

    return {
        "plain SFT": module(),
        # The same arm again: its ratio is the measurement's own noise (an A/A test).
        "plain SFT (A/A)": module(),
        "SFT + orthogonal reg.": module(OrthogonalityLoss(root / "vector", weight=1.0)),
        "aux: spatial alignment": module(SpatialAlignment()),
        "aux: reasoning": module(ReasoningCoTraining()),
        "aux: both": module(SpatialAlignment(), ReasoningCoTraining()),
    }


def step(module: VLAModule, optimizer: torch.optim.Optimizer, batch: dict) -> None:
    losses = module.compute_losses(batch)
    total = losses["action"] + sum(o.weight * losses[n] for n, o in module.objectives.items())
    optimizer.zero_grad(set_to_none=True)
    total.backward()
    optimizer.step()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--preset", default="openvla-oft-tiny")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        data = make_data(root)
        dataset = HDF5RobotDataset(
            [data], cameras=["agentview", "robot0_eye_in_hand"],
            proprio_keys=["robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"],
            chunk_size=8, load_depth=True, load_annotations=True,
        )  # fmt: skip
        batch = next(iter(torch.utils.data.DataLoader(dataset, batch_size=args.batch)))
        arms = build_arms(args.preset, data, root)
        times: dict[str, list[float]] = {name: [] for name in arms}
        for module, optimizer in arms.values():  # warm-up (allocator, lazy init)
            for _ in range(3):
                step(module, optimizer, batch)
        for _ in range(args.steps):
            for name, (module, optimizer) in arms.items():
                start = time.perf_counter()
                step(module, optimizer, batch)
                times[name].append(time.perf_counter() - start)
        memory = {}
        for name, (module, _) in arms.items():
            store: list[float] = []
            with saved_activation_bytes(store):
                losses = module.compute_losses(batch)
            memory[name] = store[0]
            del losses
    baseline = statistics.median(times["plain SFT"])
    print(
        f"{args.preset}, batch {args.batch}, {args.steps} interleaved rounds, {args.threads} thread(s)\n"
    )
    print("| arm | step time (ms, median) | ratio to plain SFT | saved activations (MiB) |")
    print("|---|---|---|---|")
    for name in arms:
        median = statistics.median(times[name])
        print(
            f"| {name} | {median * 1e3:.1f} | {median / baseline:.3f} | {memory[name] / 2**20:.1f} |"
        )


if __name__ == "__main__":
    main()
