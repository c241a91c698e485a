"""A short fit run as its own program, so Lightning can launch 2 CPU processes (gloo) for it.

Used by tests/test_distributed.py: the same run on 1 process and on 2 processes (DDP or FSDP2 via
``ModelParallelStrategy``) must give the same loss curve and the same exported weights. Several
``--backbone`` presets fit one after another in the same processes (each into ``OUT/<preset>``,
each with its own ``--vector``), so a test covering every preset starts its processes once.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import lightning as L
import torch
import torch.distributed as dist

from capvector.callbacks import ExportOnFitEnd, MergeCapabilityVector, OrthogonalRegularization
from capvector.data.datamodule import RobotDataModule
from capvector.module import VLAModule
from capvector.training.lora import LoraSettings


class RecordGlobalLoss(L.Callback):
    """Writes the loss averaged over ranks at every step (rank 0 writes the JSON file)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.losses: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # noqa: ANN001
        loss = outputs["loss"].detach().clone()
        if dist.is_initialized():
            dist.all_reduce(loss)
            loss /= dist.get_world_size()
        self.losses.append(loss.item())

    def on_fit_end(self, trainer, pl_module) -> None:  # noqa: ANN001
        if trainer.is_global_zero:
            self.path.write_text(json.dumps(self.losses))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--devices", type=int, default=1)
    parser.add_argument("--strategy", default="auto", choices=["auto", "ddp", "fsdp2"])
    parser.add_argument("--global-batch", type=int, default=4)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--backbone", nargs="+", default=["openvla-oft-tiny"])
    parser.add_argument("--pretrained", default=None)
    parser.add_argument("--activation-checkpointing", action="store_true")
    parser.add_argument("--ckpt-path", default=None)
    parser.add_argument(
        "--vector", nargs="+", default=None, help="merge at fit start (one per --backbone)"
    )
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--orth-weight", type=float, default=0.0, help="orthogonal regularization")
    parser.add_argument("--export-initial", default=None, help="export the weights before training")
    parser.add_argument("--frozen-dtype", default="float32", help="VLAModule(frozen_dtype=...)")
    parser.add_argument("--precision", default="32-true", help="Trainer(precision=...)")
    parser.add_argument(
        "--validate-episodes", type=int, default=0, help="only run rollout validation"
    )
    args = parser.parse_args(argv)
    if args.vector is not None and len(args.vector) != len(args.backbone):
        parser.error("give one --vector per --backbone")
    one_run_only = args.pretrained, args.ckpt_path, args.export_initial, args.validate_episodes
    if len(args.backbone) > 1 and any(one_run_only):
        parser.error(
            "--pretrained, --ckpt-path, --export-initial and --validate-episodes take one --backbone"
        )
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(1)
    vectors = args.vector or [None] * len(args.backbone)
    for backbone, vector in zip(args.backbone, vectors, strict=True):
        out = Path(args.out) if len(args.backbone) == 1 else Path(args.out) / backbone
        L.seed_everything(0)  # each preset's run is the one it would be alone
        run(args, backbone, vector, out)


def run(args: argparse.Namespace, backbone: str, vector: str | None, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    eval_tasks = [{"task": "Lift", "episodes": args.validate_episodes, "max_steps": 16}]
    dm = RobotDataModule(
        train_files=[args.data],
        batch_size=args.global_batch // args.devices,
        augment=False,
        shuffle=False,
        eval_tasks=eval_tasks if args.validate_episodes else None,
    )
    module = VLAModule(
        backbone=backbone,
        pretrained=args.pretrained,
        data_spec=dm.spec,
        lora=LoraSettings(r=4, alpha=8),
        activation_checkpointing=args.activation_checkpointing,
        frozen_dtype=args.frozen_dtype,
    )
    if args.export_initial:
        module.export(args.export_initial)
    callbacks: list[L.Callback] = [
        RecordGlobalLoss(out / "losses.json"),
        ExportOnFitEnd(str(out / "export")),
    ]
    if vector:
        callbacks.append(MergeCapabilityVector(vector, scale=args.scale))
        if args.orth_weight:
            callbacks.append(OrthogonalRegularization(vector, weight=args.orth_weight, mode="lora"))
    strategy: object = args.strategy
    if args.strategy == "fsdp2":
        from lightning.pytorch.strategies import ModelParallelStrategy

        strategy = ModelParallelStrategy(
            data_parallel_size=args.devices,
            tensor_parallel_size=1,
            save_distributed_checkpoint=False,
        )
    elif args.strategy == "ddp":
        from lightning.pytorch.strategies import DDPStrategy

        strategy = DDPStrategy(process_group_backend="gloo")
    trainer = L.Trainer(
        accelerator="cpu",
        devices=args.devices,
        strategy=strategy,
        max_steps=args.steps,
        precision=args.precision,
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=1.0 if args.validate_episodes else 0,
        default_root_dir=out,
        callbacks=callbacks,
    )
    if args.validate_episodes:
        (metrics,) = trainer.validate(module, dm)
        if trainer.is_global_zero:
            (out / "validate.json").write_text(
                json.dumps({k: float(v) for k, v in metrics.items()})
            )
        return
    trainer.fit(module, dm, ckpt_path=args.ckpt_path)
    trainer.save_checkpoint(out / "last.ckpt")


if __name__ == "__main__":
    main()
