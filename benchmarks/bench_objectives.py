"""What the auxiliary objectives add to a training step: plain SFT against SFT plus each objective,
on one batch of demos (forward, backward and AdamW step, as ``capvector fit`` runs them; data
loading left out, it is the same for every arm). The arms alternate, round by round, in this
process, so machine load hits them alike; the table gives each arm's median and its ratio to plain
SFT.

    python benchmarks/bench_objectives.py --data DEMOS [--pretrained EXPORT] [--cameras ...]
        [--proprio-keys ...] [--batch 16] [--rounds 5] [--steps 4] [--arms NAME ...]

For LIBERO's layout: ``--cameras agentview robot0_eye_in_hand --proprio-keys ee_states
gripper_states`` (configs/recipes/libero_train.yaml).

Every arm holds a model of its own: about 2 GB each for the mini (``--pretrained`` a mini export),
so pick the arms with ``--arms`` where memory is short.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from capvector.backbones.base import IGNORE_INDEX, VLABackbone, VLAOutput
from capvector.data.batch import Batch
from capvector.data.datamodule import RobotDataModule, noise_seeds
from capvector.module import VLAModule
from capvector.objectives import GeometricTeacher, Objective, ReasoningCoTraining, SpatialAlignment


def spatial() -> Objective:
    """configs/recipes/aux_sft.yaml's spatial alignment."""
    return SpatialAlignment(
        weight=0.5, teacher=GeometricTeacher(feature_dim=64, position_embedding=True)
    )


class ReasoningEveryPosition(ReasoningCoTraining):
    """Reasoning co-training as it was before ``answer_logits``: every position of the text pass
    projected onto the vocabulary, then all but the answer positions ignored. The same loss: the
    baseline of that change."""

    def forward(self, batch: Batch, output: VLAOutput, backbone: VLABackbone) -> Tensor:
        logits, labels = backbone.language_model_logits(*self.text_inputs(batch))
        return F.cross_entropy(
            logits[:, :-1].flatten(0, 1).float(), labels[:, 1:].flatten(), ignore_index=IGNORE_INDEX
        )


ARMS: dict[str, Callable[[], list[Objective]]] = {
    "plain SFT": lambda: [],
    "+ spatial alignment": lambda: [spatial()],
    "+ reasoning, every sample": lambda: [ReasoningCoTraining(weight=0.1)],
    "+ reasoning, 4 samples": lambda: [ReasoningCoTraining(weight=0.1, samples=4)],
    "+ reasoning, 4 samples, every position projected": lambda: [
        ReasoningEveryPosition(weight=0.1, samples=4)
    ],
    "+ reasoning, 2 samples": lambda: [ReasoningCoTraining(weight=0.1, samples=2)],
    "+ reasoning, 2 samples, answer vocabulary": lambda: [
        ReasoningCoTraining(weight=0.1, samples=2, vocabulary="answers")
    ],
    "aux_sft.yaml (spatial + reasoning on 4)": lambda: [
        spatial(),
        ReasoningCoTraining(weight=0.1, samples=4),
    ],
    "mini_study_aux.yaml (spatial + reasoning on 2, answer vocabulary)": lambda: [
        spatial(),
        ReasoningCoTraining(weight=0.1, samples=2, vocabulary="answers"),
    ],
}


def step_function(
    args: argparse.Namespace, data: RobotDataModule, batch: dict, objectives: list[Objective]
) -> Callable[[], None]:
    torch.manual_seed(0)
    if args.pretrained:
        module = VLAModule(pretrained=str(args.pretrained), data_spec=data.spec)
    else:
        module = VLAModule(backbone=args.preset, data_spec=data.spec)
    for objective in objectives:  # as AuxiliaryObjective.setup attaches them
        objective.bind(module.backbone)
        objective.bind_data(data.train_dataset, module.backbone)
        module.add_objective(objective)
    optimizer = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=1e-4)

    def step() -> None:
        losses = module.compute_losses(batch)
        total = losses["action"] + sum(o.weight * losses[o.name] for o in objectives)
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()

    return step


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", type=Path, required=True, help="demo file or folder (with depth)")
    parser.add_argument("--pretrained", type=Path, help="an export to start from")
    parser.add_argument("--preset", default="openvla-oft-tiny")
    parser.add_argument("--cameras", nargs="+", default=["agentview", "robot0_eye_in_hand"])
    parser.add_argument("--proprio-keys", nargs="+")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--arms", nargs="+", choices=list(ARMS), default=list(ARMS),
        help="the arms to time (plain SFT always runs: the baseline)",
    )  # fmt: skip
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    more = {"proprio_keys": args.proprio_keys} if args.proprio_keys else {}
    data = RobotDataModule(
        train_files=[str(args.data)], batch_size=args.batch, cameras=args.cameras,
        load_depth=True, load_annotations=True, **more,
    )  # fmt: skip
    batch = next(iter(data.train_dataloader()))
    batch["noise_seed"] = noise_seeds(batch["index"], 0, seed=0)  # as the fit's batches carry
    names = ["plain SFT", *(name for name in args.arms if name != "plain SFT")]
    steps = {name: step_function(args, data, batch, ARMS[name]()) for name in names}
    for step in steps.values():  # warm-up (allocator, lazy init)
        step()
    seconds: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(args.rounds):
        for name, step in steps.items():
            began = time.perf_counter()
            for _ in range(args.steps):
                step()
            seconds[name].append((time.perf_counter() - began) / args.steps)
    base = statistics.median(seconds["plain SFT"])
    print(
        f"{args.rounds} rounds of {args.steps} steps, batch {args.batch}, {args.threads} thread(s)\n"
    )
    print("| arm | s/step (median) | × plain SFT |")
    print("|---|---|---|")
    for name, values in seconds.items():
        median = statistics.median(values)
        print(f"| {name} | {median:.3f} | {median / base:.2f} |")


if __name__ == "__main__":
    main()
