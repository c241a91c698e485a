"""``capvector sweep-scale``: choose the merge scale λ by MuJoCo rollouts on validation seeds.

For each λ the vector is merged in memory (θ_pre + λ·c, never written unless asked), optionally
fine-tuned for a few steps with the orthogonal regularization, then scored by the module's own
validation loop (``trainer.validate``): the action L1 on held-out demos and rollouts on validation
seeds, which are disjoint from the evaluation seeds used for reporting (as the task-vector
literature picks λ on held-out validation data). The model, data module and trainer are those of
``capvector fit --config FIT --model.pretrained θ_pre`` (``--fit-config FIT``); without one, quiet
defaults from θ_pre's data spec and the options. Results go to ``<out>/sweep.json`` after every λ,
so an interrupted sweep resumes where it stopped; each λ's logs to ``<out>/scale_<λ>/``.
"""

from __future__ import annotations

import dataclasses
import json
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lightning.pytorch.loggers import Logger
from tqdm import tqdm

from capvector.data.episodes import EpisodeDataset, eval_task
from capvector.data.spec import DataSpec
from capvector.data.statistics import BOUNDS_Q99
from capvector.envs.base import EVAL_SEED_START, VALIDATION_SEED_START
from capvector.envs.registry import get_suite
from capvector.errors import CapVectorError
from capvector.eval.device import Precision, resolve_device, resolve_precision
from capvector.eval.results import best_scale, success_cell, wilson_interval
from capvector.io.hub import local_folder
from capvector.io.loading import read_json
from capvector.io.names import DATA_SPEC_FILE
from capvector.io.outputs import atomic_write_bytes, atomic_write_file, check_output
from capvector.tool_cli import run_tool
from capvector.training.loggers import log_figure


def fit_settings(
    base: str,
    fit_configs: Sequence[str] = (),
    task: str | None = None,
    episodes: int = 0,
    robot: str = "Panda",
    demos: str | None = None,
    device: str | None = None,
    precision: Precision | None = None,
) -> Any:
    """The sweep's model, data and trainer settings, parsed by ``capvector fit``'s LightningCLI
    (``trainer:``, ``data:`` and ``model:`` mean what they mean there), with θ_pre as
    ``model.pretrained``. Without ``fit_configs``: a quiet trainer (accelerator auto, one device)
    and a data module of ``demos`` (training and held-out) shaped as θ_pre's data.
    ``task``/``episodes`` replace ``data.eval_tasks``, ``demos`` sets ``data.val_files``; every
    rollout task starts at ``VALIDATION_SEED_START`` or above, never on evaluation seeds.
    ``device``/``precision`` set the trainer's (``trainer_placement``). Returns the CLI
    (``parser``, ``config``) without building anything."""

    from capvector.backbones.base import load_export_config
    from capvector.workflows.fit import run_lightning_cli

    with warnings.catch_warnings():  # the args are ours, never sys.argv: nothing is shadowed
        warnings.filterwarnings("ignore", "LightningCLI's args parameter")
        cli = run_lightning_cli([a for c in fit_configs for a in ("--config", c)], run=False)
    config = cli.config
    if task and episodes:
        config["data.eval_tasks"] = [{"task": task, "episodes": episodes, "robot": robot}]
    if demos:
        config["data.val_files"] = [demos]
    data = config.data
    if not (data.eval_tasks or data.val_files or data.val_episodes):
        raise CapVectorError(
            "give --task/--episodes (rollouts) and/or --demos (held-out L1), or a --fit-config "
            "whose data has eval_tasks or val_files"
        )
    check_no_merge_callback(config.trainer.callbacks)
    tasks = [eval_task(t) for t in data.eval_tasks or []]
    for t in tasks:  # validation seeds, never the evaluation ones
        if not get_suite(t.suite).seeded:
            raise CapVectorError(
                f"data.eval_tasks has {t.task} ({t.suite}), whose episodes start from the fixed "
                "initial states that evaluation reports: choosing λ on them would tune on the "
                "test episodes; sweep with seeded tasks (robosuite's) or held-out demos (--demos)"
            )
        start = t.options.get("start_seed") or EVAL_SEED_START
        t.options["start_seed"] = max(start, VALIDATION_SEED_START)
    config["data.eval_tasks"] = [dataclasses.asdict(t) for t in tasks]
    EpisodeDataset(tasks)  # an unknown task fails here
    load_export_config(base)  # an export folder, before any work
    config["model.pretrained"] = base
    if not fit_configs:
        for key, value in quiet_defaults(base_data_spec(base), demos).items():
            config[key] = value
    for key, value in trainer_placement(device, precision, defaults=not fit_configs).items():
        config[key] = value
    return cli


def check_no_merge_callback(callbacks: Any) -> None:
    """The sweep merges θ_pre + λc itself, in memory: a ``MergeCapabilityVector`` in the fit
    config's callbacks would merge a vector again when a λ is fine-tuned (``--finetune-steps``)."""
    listed = callbacks if isinstance(callbacks, list) else [callbacks] if callbacks else []
    for callback in listed:
        class_path = str(getattr(callback, "class_path", ""))
        if class_path.rsplit(".", 1)[-1] == "MergeCapabilityVector":
            raise CapVectorError(
                f"the --fit-config's trainer.callbacks has {class_path}: sweep-scale merges "
                "θ_pre + λc itself, so each λ would get a vector merged a second time; give the "
                "fit config without that callback (the downstream arm's config before the merge)"
            )


def trainer_placement(
    device: str | None, precision: Precision | None, defaults: bool
) -> dict[str, Any]:
    """``--device``/``--precision`` as the trainer's accelerator, devices and precision, which
    every λ's fine-tuning and validation run on (``device`` ``cuda:1``: accelerator ``cuda``,
    devices ``[1]``). What is not given stays the fit config's; with ``defaults`` (no fit
    config) it is the tools' default: CUDA with bf16 autocast when there is a GPU, else the CPU
    in float32."""
    torch_device = resolve_device(device)
    settings: dict[str, Any] = {}
    if device is not None or defaults:
        settings["trainer.accelerator"] = torch_device.type  # cpu, cuda, mps: Lightning's names
        settings["trainer.devices"] = 1 if torch_device.index is None else [torch_device.index]
    if precision is not None or defaults:
        settings["trainer.precision"] = resolve_precision(torch_device, precision)
    return settings


def quiet_defaults(spec: DataSpec, demos: str | None) -> dict[str, Any]:
    """The settings of a sweep without ``--fit-config``: no progress bars, checkpoints or videos,
    and ``demos`` (if any) as training data shaped as θ_pre's (the device: ``trainer_placement``).
    """
    return {
        "seed_everything": 0,
        "trainer.enable_progress_bar": False,
        "trainer.enable_model_summary": False,
        "trainer.enable_checkpointing": False,
        "model.rollout": {"videos": 0},
        "data.train_files": [demos] if demos else None,
        "data.cameras": list(spec.cameras),
        "data.proprio_keys": list(spec.proprio_keys),
        "data.chunk_size": spec.chunk_size,
        "data.dataset_name": spec.dataset_name,
        "data.augment": spec.center_crop,  # evaluated with the crop θ_pre was trained with
        "data.normalization": spec.stats_entry.get("normalization", BOUNDS_Q99),
    }


def base_data_spec(base: str) -> DataSpec:
    """θ_pre's data spec, which shapes the data module of a sweep without ``--fit-config``."""
    path = local_folder(base, "--base") / DATA_SPEC_FILE
    if not path.is_file():
        raise CapVectorError(
            f"--base {base} has no {DATA_SPEC_FILE} (an import, or not a capvector export): "
            "give a --fit-config whose data section describes the data"
        )
    return DataSpec(**read_json(path))


def score_scale(
    cli: Any,
    vector: str,
    loaded: Any,
    scale: float,
    log_dir: Path,
    finetune_steps: int = 0,
    orth_weight: float = 1.0,
    allow_large_scale: bool = False,
) -> dict[str, Any]:
    """θ_pre + scale·c (``loaded``: the ``vector`` folder's) merged in memory, fine-tuned
    ``finetune_steps`` steps, then validated by ``trainer.validate`` on the configured trainer and
    data module; the row of what the loop logged. Logs go to ``log_dir``."""
    import lightning as L
    from jsonargparse import Namespace

    from capvector.vectors import apply_vector_
    from capvector.vectors.precision import MergePrecision

    config = cli.config.clone()
    config["trainer.default_root_dir"] = str(log_dir)
    config["trainer.logger"] = Namespace(
        class_path="capvector.training.loggers.CSVLogger",
        init_args=Namespace(save_dir=str(log_dir.parent), name=log_dir.name),
    )
    if config.seed_everything is not False:  # an int once parsed: each λ as in a fresh sweep
        L.seed_everything(config.seed_everything, workers=True)
    built = cli.parser.instantiate_classes(config)
    module, datamodule = built.model, built.data
    precision = MergePrecision()
    apply_vector_(module.backbone, loaded, scale, precision, allow_large_scale)
    # Before configure_model casts frozen weights (model.frozen_dtype): λc stays float32.
    module.float32_parameters.update(loaded.changed_keys())
    trainer_settings = {**built.trainer}
    if finetune_steps:
        finetune(module, datamodule, trainer_settings, vector, finetune_steps, orth_weight)
    trainer = L.Trainer(**trainer_settings)
    trainer.validate(module, datamodule, verbose=False)
    return {
        "scale": scale,
        "merge_relative_error": precision.relative_error(),
        **validation_row(trainer.callback_metrics),
    }


def finetune(
    module: Any,
    datamodule: Any,
    trainer_settings: Mapping[str, Any],
    vector: str,
    steps: int,
    orth_weight: float,
) -> None:
    """``steps`` steps of the configured training, without validation, plus the orthogonal
    regularization along the vector (``orth_weight`` 0: none)."""
    import lightning as L

    from capvector.callbacks import OrthogonalRegularization

    callbacks = trainer_settings.get("callbacks") or []
    callbacks = list(callbacks) if isinstance(callbacks, list) else [callbacks]
    if orth_weight:
        callbacks.append(OrthogonalRegularization(vector, weight=orth_weight))
    trainer = L.Trainer(**{
        **trainer_settings, "max_steps": steps, "max_epochs": None, "limit_val_batches": 0,
        "num_sanity_val_steps": 0, "callbacks": callbacks,
    })  # fmt: skip
    trainer.fit(module, datamodule)
    for name in list(module.objectives):  # training-only loss terms
        module.remove_objective(name)


def validation_row(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """Held-out L1 and rollout success as the validation loop logged them (``val/...``)."""
    row: dict[str, Any] = {}
    if "val/action_l1" in metrics:
        row["held_out_l1"] = float(metrics["val/action_l1"])
    if "val/episodes" in metrics:
        episodes = round(float(metrics["val/episodes"]))
        successes = round(float(metrics["val/success_rate"]) * episodes)
        row.update(episodes=episodes, successes=successes, success_rate=successes / episodes,
                   ci95=list(wilson_interval(successes, episodes)))  # fmt: skip
    return row


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
    fit_configs: Sequence[str] = (),
    device: str | None = None,
    precision: Precision | None = None,
) -> list[dict[str, Any]]:
    from capvector.vectors import load_vector
    from capvector.vectors.merge import check_scale

    for scale in scales:  # all of them before the first (minutes-long) λ
        check_scale(scale, vector, allow_large_scale)
    cli = fit_settings(base, fit_configs, task, episodes, robot, demos, device, precision)
    data = cli.config.data
    if finetune_steps and not (data.train_files or data.lerobot_root):
        raise CapVectorError(
            "--finetune-steps needs training data: --demos (the downstream training demos), or "
            "data.train_files in --fit-config"
        )
    c = load_vector(vector)  # a bad task or vector fails before the output folder is made
    out_dir = check_output(out, overwrite=True, inputs=[base, vector, demos, *fit_configs])
    out_dir.mkdir(parents=True, exist_ok=True)  # resumed when there
    results_path = out_dir / "sweep.json"
    rows: list[dict[str, Any]] = (
        json.loads(results_path.read_text()) if results_path.is_file() else []
    )
    done = {row["scale"] for row in rows}
    for scale in tqdm(scales, desc="λ", unit="scale"):
        if scale in done:
            continue
        log_dir = out_dir / f"scale_{scale:g}"
        rows.append(score_scale(
            cli, vector, c, scale, log_dir, finetune_steps, orth_weight, allow_large_scale
        ))  # fmt: skip
        rows.sort(key=lambda r: r["scale"])
        atomic_write_bytes(results_path, json.dumps(rows, indent=2).encode())  # resumable
    return [r for r in rows if r["scale"] in scales]


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
    fit_config: list[str] | None = None,
    logger: Logger | None = None,
    device: str | None = None,
    precision: Precision | None = None,
) -> None:
    """Choose the merge scale λ by the validation loop: rollouts on validation seeds and the
    held-out L1.

    Args:
        base: θ_pre: export folder (capvector export)
        vector: capability vector folder
        out: folder for sweep.json and sweep.png
        scales: λ values, e.g. 0,0.5,1
        task: robosuite task for validation rollouts
        episodes: validation episodes per λ
        demos: held-out demos (HDF5) for the action L1
        finetune_steps: downstream SFT steps per λ
        orth_weight: weight of the orthogonal regularization while fine-tuning
        allow_large_scale: accept |λ| > 100 in --scales
        fit_config: `capvector fit` configs: their trainer, data and model settings
        logger: a Lightning logger to show the plot in as well, given as in a fit config's
            trainer.logger (TensorBoard, W&B and MLflow show it)
        device: where each λ is fine-tuned and validated (the trainer's accelerator and
            devices), e.g. cpu, cuda, cuda:1 (default: the fit config's; without one, cuda when
            there is one)
        precision: the trainer's precision, 32-true, bf16-mixed or 16-mixed (default: the fit
            config's; without one, bf16-mixed on a GPU, 32-true elsewhere)
    """
    try:
        values = [float(s) for s in scales.split(",")]
    except ValueError:
        raise CapVectorError(f"--scales takes numbers like 0,0.5,1, got {scales!r}") from None
    rows = sweep(base, vector, values, out, task, episodes, robot, demos, finetune_steps,
                 orth_weight, allow_large_scale, fit_config or [], device, precision)  # fmt: skip
    plot(rows, Path(out) / "sweep.png")
    if logger is not None:
        log_figure([logger], "sweep/scale", Path(out) / "sweep.png")
        logger.finalize("success")
    print(format_table(rows))
    print(f"\nbest λ = {best_scale(rows):g}  (plot: {Path(out) / 'sweep.png'})")
