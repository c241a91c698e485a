"""``capvector sweep-scale``: choose the merge scale λ by MuJoCo rollouts on validation seeds.

For each λ the vector is merged in memory (θ_pre + λ·c, never written unless asked), optionally
fine-tuned for a few steps with the orthogonal regularization, then scored by the action-prediction
L1 on held-out demos and by rollouts on validation seeds, which are disjoint from the evaluation
seeds used for reporting (as the task-vector literature picks λ on held-out validation data).
Results go to ``<out>/sweep.json`` after every λ, so an interrupted sweep resumes where it stopped.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from capvector.data.episodes import EvalTask
from capvector.errors import CapVectorError
from capvector.eval.episodes import VALIDATION_SEED_START
from capvector.eval.results import success_cell, wilson_interval
from capvector.io.outputs import atomic_write_bytes, atomic_write_file, check_output
from capvector.module import held_out_action_l1, load_module
from capvector.tool_cli import run_tool


def held_out_l1(module: Any, demos: str, batch_size: int = 16) -> float:
    """Mean action L1 of the module on every chunk of ``demos`` (normalised action space)."""
    from capvector.data.hdf5 import HDF5RobotDataset
    from capvector.data.transforms import ImageTransform

    spec = module.data_spec
    dataset = HDF5RobotDataset(
        [demos], cameras=spec.cameras, proprio_keys=spec.proprio_keys, chunk_size=spec.chunk_size,
        statistics=spec.stats_entry, transform=ImageTransform(augment=False, center_crop=spec.center_crop),
    )  # fmt: skip
    total, count = 0.0, 0
    with torch.no_grad():
        for batch in torch.utils.data.DataLoader(dataset, batch_size=batch_size):
            n = len(batch["instruction"])
            total += float(held_out_action_l1(module.backbone, batch)) * n
            count += n
    return total / count


def finetune(module: Any, vector: str, demos: str, steps: int, orth_weight: float) -> None:
    import lightning as L

    from capvector.callbacks import OrthogonalRegularization
    from capvector.data.datamodule import RobotDataModule

    spec = module.data_spec
    dm = RobotDataModule(train_files=[demos], cameras=spec.cameras, proprio_keys=spec.proprio_keys,
                         chunk_size=spec.chunk_size, batch_size=8)  # fmt: skip
    callbacks = [OrthogonalRegularization(vector, weight=orth_weight)] if orth_weight else []
    trainer = L.Trainer(
        max_steps=steps, accelerator="cpu", logger=False, enable_progress_bar=False,
        enable_model_summary=False, enable_checkpointing=False, limit_val_batches=0,
        callbacks=callbacks,
    )  # fmt: skip
    trainer.fit(module, dm)
    for name in list(module.objectives):
        module.remove_objective(name)


def sweep(
    base: str,
    vector: str,
    scales: list[float],
    out: str,
    task: str | None = None,
    episodes: int = 0,
    robot: str = "Panda",
    demos: str | None = None,
    finetune_steps: int = 0,
    orth_weight: float = 1.0,
    allow_large_scale: bool = False,
) -> list[dict[str, Any]]:
    from capvector.data.episodes import EpisodeDataset
    from capvector.eval.policy import VLAPolicy
    from capvector.eval.rollout import RolloutEvaluator
    from capvector.vectors import apply_vector_, load_vector
    from capvector.vectors.merge import check_scale
    from capvector.vectors.precision import MergePrecision

    if finetune_steps and demos is None:
        raise CapVectorError("--finetune-steps needs --demos (the downstream training demos)")
    for scale in scales:  # all of them before the first (minutes-long) λ
        check_scale(scale, vector, allow_large_scale)
    specs = (
        EpisodeDataset([EvalTask(task, episodes, robot, VALIDATION_SEED_START)]).specs
        if task and episodes
        else []
    )
    c = load_vector(vector)  # a bad task or vector fails before the output folder is made
    out_dir = check_output(out, overwrite=True, inputs=[base, vector, demos])  # resumed when there
    out_dir.mkdir(parents=True, exist_ok=True)
    results_path = out_dir / "sweep.json"
    rows: list[dict[str, Any]] = (
        json.loads(results_path.read_text()) if results_path.is_file() else []
    )
    done = {row["scale"] for row in rows}
    for scale in tqdm(scales, desc="λ", unit="scale"):
        if scale in done:
            continue
        module = load_module(base)  # float32 weights: the merge keeps all of λc (recorded)
        precision = MergePrecision()
        apply_vector_(module.backbone, c, scale, precision, allow_large_scale)
        if finetune_steps:
            finetune(module, vector, demos, finetune_steps, orth_weight)
        module.eval()
        row: dict[str, Any] = {"scale": scale, "merge_relative_error": precision.relative_error()}
        if demos:
            row["held_out_l1"] = held_out_l1(module, demos)
        if specs:
            spec = module.data_spec
            evaluator = RolloutEvaluator(spec.cameras, spec.image_size, spec.camera_fovy)
            results = evaluator.run(VLAPolicy(module.backbone, spec), specs)
            successes = sum(r.success for r in results)
            row.update(episodes=len(specs), successes=successes, success_rate=successes / len(specs),
                       ci95=list(wilson_interval(successes, len(specs))))  # fmt: skip
        rows.append(row)
        rows.sort(key=lambda r: r["scale"])
        atomic_write_bytes(results_path, json.dumps(rows, indent=2).encode())  # resumable
    return [r for r in rows if r["scale"] in scales]


def best_scale(rows: list[dict[str, Any]]) -> float:
    """Highest success rate; ties (and sweeps without rollouts) go to the lowest held-out L1."""
    return min(rows, key=lambda r: (-r.get("success_rate", 0.0), r.get("held_out_l1", 0.0)))[
        "scale"
    ]


def format_table(rows: list[dict[str, Any]]) -> str:
    lines = ["| λ | success (n; 95% CI) | held-out L1 |", "|---|---|---|"]
    for r in rows:
        success = success_cell(r["successes"], r["episodes"]) if "successes" in r else "–"
        l1 = f"{r['held_out_l1']:.4f}" if "held_out_l1" in r else "–"
        lines.append(f"| {r['scale']:g} | {success} | {l1} |")
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = [r["scale"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if all("success_rate" in r for r in rows):
        rates = [r["success_rate"] for r in rows]
        low = [r["success_rate"] - r["ci95"][0] for r in rows]
        high = [r["ci95"][1] - r["success_rate"] for r in rows]
        ax.errorbar(
            scales, rates, yerr=[low, high], marker="o", capsize=3, label="success rate (95% CI)"
        )
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.02, 1.02)
    if all("held_out_l1" in r for r in rows):
        other = ax.twinx() if all("success_rate" in r for r in rows) else ax
        other.plot(
            scales, [r["held_out_l1"] for r in rows], "s--", color="tab:orange", label="held-out L1"
        )
        other.set_ylabel("held-out action L1")
    fig.legend(loc="upper center", bbox_to_anchor=(0.5, 0.9), fontsize=8)
    ax.set_xlabel("merge scale λ")
    ax.set_title("θ_pre + λ·c")
    fig.tight_layout()
    with atomic_write_file(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    return run_tool(sweep_cli, argv, "sweep-scale")


def sweep_cli(
    base: str,
    vector: str,
    out: str,
    scales: str = "0,0.25,0.5,0.75,1,1.25,1.5",
    task: str | None = None,
    robot: str = "Panda",
    episodes: int = 0,
    demos: str | None = None,
    finetune_steps: int = 0,
    orth_weight: float = 1.0,
    allow_large_scale: bool = False,
) -> None:
    """Choose the merge scale λ by MuJoCo rollouts on validation seeds and the held-out L1.

    Args:
        base: θ_pre: export folder or checkpoint
        vector: capability vector folder
        out: folder for sweep.json and sweep.png
        scales: λ values, e.g. 0,0.5,1
        task: robosuite task for validation rollouts
        episodes: validation episodes per λ
        demos: held-out demos (HDF5) for the action L1
        finetune_steps: downstream SFT steps per λ
        orth_weight: weight of the orthogonal regularization while fine-tuning
        allow_large_scale: accept |λ| > 100 in --scales
    """
    try:
        values = [float(s) for s in scales.split(",")]
    except ValueError:
        raise CapVectorError(f"--scales takes numbers like 0,0.5,1, got {scales!r}") from None
    if not (task and episodes) and not demos:
        raise CapVectorError("give --task/--episodes (rollouts) and/or --demos (held-out L1)")
    rows = sweep(base, vector, values, out, task, episodes, robot, demos, finetune_steps,
                 orth_weight, allow_large_scale)  # fmt: skip
    plot(rows, Path(out) / "sweep.png")
    print(format_table(rows))
    print(f"\nbest λ = {best_scale(rows):g}  (plot: {Path(out) / 'sweep.png'})")
