"""VLAModule: thin Lightning wiring around a backbone and a set of named loss terms."""

from __future__ import annotations

import csv
import dataclasses
import inspect
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor, nn
from torchmetrics import SumMetric

from capvector.backbones.base import (
    BackboneError,
    OutputRequest,
    VLABackbone,
    backbone_class,
    build_backbone,
    load_export_config,
)
from capvector.backbones.materialize import build_stored_in, load_pretrained, reload_in_float32
from capvector.data.batch import Batch
from capvector.data.episodes import EpisodeDataset, EpisodeItem, is_episode_batch
from capvector.data.spec import DataSpec
from capvector.envs.base import Spec
from capvector.envs.registry import suite_of
from capvector.errors import CapVectorError
from capvector.eval.device import native_bf16_cpu
from capvector.eval.metrics import SuccessRate
from capvector.eval.results import metric_key
from capvector.io.hub import local_folder
from capvector.io.loading import load_torch, read_json
from capvector.io.lora_layers import constant_scaling, lora_form_state, merged_lora_view
from capvector.io.names import (
    BASE_DELTA,
    CHECKPOINT_METADATA,
    DATA_SPEC_FILE,
    EPISODE_COLUMNS,
    EPISODES_LOG,
    MERGED_VECTORS,
    STATISTICS_FILE,
    SUCCESS_BY_TASK,
    VALIDATION_PROGRESS,
    CheckpointMetadata,
)
from capvector.io.tensors import LazyTensors, TensorInfo, all_finite, tensor_info
from capvector.io.weights import dtype_name, parse_dtype
from capvector.objectives.base import Objective, compute_losses
from capvector.policy import VLAPolicy
from capvector.training.distributed import full_state_dict, is_rank_zero, parallelize
from capvector.training.loggers import log_file, log_video, logging_step, run_folder
from capvector.training.lora import (
    LoraSettings,
    cast_frozen_parameters,
    frozen_dtype_of,
    set_trainable,
)
from capvector.vectors import MergedVector, read_record, record_dicts


@dataclass
class RolloutSettings:
    """How the validation loop runs MuJoCo episodes (which episodes: ``data.eval_tasks``)."""

    videos: int = 2
    """Write mp4s of the first this-many episodes of each validation run."""
    execute_steps: int | None = None
    """Execute only the first k actions of each chunk (None: the whole chunk, as OpenVLA-OFT)."""
    batch_size: int = 8
    """Episodes in flight at once, one batched policy forward for all (1: one at a time). Each
    LIBERO episode in flight holds an env of its own (~1.2 GB)."""
    workers: int | None = None
    """Processes stepping the simulators (0: this one); None: one per usable core, up to
    ``batch_size`` (``capvector.eval.rollout.default_workers``)."""


@dataclass
class OptimizerSettings:
    """AdamW + schedule. Defaults follow OpenVLA-OFT: lr 5e-4, torch AdamW defaults, no warmup."""

    lr: float = 5e-4
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.999)
    schedule: str = "constant"
    """'constant', 'cosine' (to min_lr_ratio * lr at the trainer's max_steps) or 'step'."""
    warmup_steps: int = 0
    decay_steps: list[int] = field(default_factory=list)
    """'step' schedule: multiply by decay_factor at these steps (OFT: x0.1 at 100k)."""
    decay_factor: float = 0.1
    min_lr_ratio: float = 1e-3


class VLAModule(L.LightningModule):
    """A backbone plus named loss terms: loss = action loss + sum of weighted objectives."""

    def __init__(
        self,
        backbone: str | None = None,
        backbone_overrides: dict[str, Any] | None = None,
        pretrained: str | None = None,
        data_spec: DataSpec | None = None,
        lora: LoraSettings | None = None,
        optimizer: OptimizerSettings | None = None,
        activation_checkpointing: bool = False,
        rollout: RolloutSettings | None = None,
        frozen_dtype: str = "float32",
    ) -> None:
        """
        Args:
            backbone: a registered preset (``capvector backbone-info --list``), or
                ``module:preset`` for a backbone defined in any importable module; unset, the
                architecture is ``pretrained``'s, or ``openvla-oft-tiny`` without ``pretrained``.
                When both are given they must name the same preset.
            backbone_overrides: config fields to change, e.g. ``{head_blocks: 1}``.
            pretrained: an export folder (θ_pre) to start from instead of random weights; its
                architecture is the model's.
            data_spec: cameras, shapes and statistics; the CLI links it from the datamodule.
                Unset (a data module without training data), ``pretrained``'s own.
            lora: fine-tune with LoRA (only LoRA and the heads train) instead of all weights.
            optimizer: AdamW and learning-rate schedule; unset, the backbone family's
                (``optimizer_preset`` in its ``configuration.py``).
            activation_checkpointing: recompute the backbone's blocks (``shard_units``) in the
                backward pass instead of storing their activations.
            rollout: videos and chunk execution of the MuJoCo validation loop.
            frozen_dtype: storage dtype of every parameter that does not train (``bfloat16`` halves
                the frozen weights of a LoRA fine-tune, as OpenVLA-OFT's recipe keeps its 7.5 B
                base in bf16); what trains (LoRA, heads, objective projectors) and what
                ``MergeCapabilityVector`` merges stay float32. Needs ``trainer.precision:
                bf16-mixed`` (autocast computes in bf16; float32 inputs meet bf16 weights).
        """
        super().__init__()
        self.save_hyperparameters()
        # Settings arrive as dataclasses (CLI, Python) or plain dicts (YAML, checkpoints); the
        # checkpoint keeps plain dicts so it loads with torch.load(weights_only=True).
        if data_spec is None and pretrained is not None:
            data_spec = _export_data_spec(pretrained)
        data_spec = _as(DataSpec, data_spec)
        lora = _as(LoraSettings, lora)
        optimizer = _as(OptimizerSettings, optimizer)
        rollout = _as(RolloutSettings, rollout)
        for name, value in (
            ("data_spec", data_spec),
            ("lora", lora),
            ("optimizer", optimizer),
            ("rollout", rollout),
        ):
            self.hparams[name] = None if value is None else dataclasses.asdict(value)
        self.data_spec = data_spec or DataSpec()
        self.lora_settings = lora
        overrides = {**self.data_spec.backbone_overrides(), **(backbone_overrides or {})}
        self.frozen_dtype = frozen_dtype_of(frozen_dtype)
        self.backbone: VLABackbone = self._build_backbone(
            backbone, pretrained, overrides, lora, self.frozen_dtype
        )
        # Unset, the family's own (its configuration.py's optimizer_preset), as LeRobot's
        # use_policy_training_preset: a config that sets model.optimizer sets all of it.
        self.optimizer_settings = optimizer or OptimizerSettings(
            **self.backbone.config.optimizer_preset
        )
        # Vectors merged into these weights (by fingerprint and λ): θ_pre's own record, then what
        # MergeCapabilityVector adds. Saved in checkpoints and exports so no vector is merged twice.
        self.merged_vectors: list[MergedVector] = (
            read_record(load_export_config(pretrained).get(MERGED_VECTORS)) if pretrained else []
        )
        self.objectives = nn.ModuleDict()
        self.activation_checkpointing = activation_checkpointing
        self.float32_parameters: set[str] = set()
        """Names (without wrapper modules) kept in float32 even when frozen: callbacks add the
        parameters a capability vector is merged into, so λc is not rounded away."""
        self.rollout = rollout or RolloutSettings()
        self.success_rates = nn.ModuleDict()
        self.episode_count = SumMetric()
        self._episode_rows: list[list[Any]] = []
        self._parallelized = False
        self._pretrained = pretrained

    @staticmethod
    def _build_backbone(
        preset: str | None,
        pretrained: str | None,
        overrides: dict[str, Any],
        lora: LoraSettings | None,
        frozen_dtype: torch.dtype,
    ) -> VLABackbone:
        """The backbone with what does not train already in ``frozen_dtype`` (built so, never a
        float32 copy of the whole model: ``backbones.materialize``), what trains in float32."""

        def prepare(model: VLABackbone) -> None:
            set_trainable(model, lora)
            if frozen_dtype != torch.float32:
                cast_frozen_parameters(model, frozen_dtype, keep=set())

        if pretrained is None:
            model = build_stored_in(
                lambda: build_backbone(preset or DEFAULT_PRESET, **overrides), frozen_dtype
            )
            assert isinstance(model, VLABackbone)
            prepare(model)
            return model
        config = load_export_config(pretrained)["backbone_config"]
        if preset is not None and preset != config["preset"]:
            raise BackboneError(
                f"model.backbone is {preset!r} but model.pretrained {pretrained} is a "
                f"{config['preset']!r} model: drop model.backbone (the export decides the "
                "architecture) or point model.pretrained at a model of that preset"
            )
        clashes = {
            k: (config[k], v) for k, v in overrides.items() if k in config and config[k] != v
        }
        if clashes:
            raise BackboneError(
                f"the data does not fit the pretrained model {pretrained}: "
                + ", ".join(
                    f"{k} is {a} in the model but {b} in the data" for k, (a, b) in clashes.items()
                )
            )
        return load_pretrained(pretrained, frozen_dtype, prepare)

    def configure_model(self) -> None:
        """FSDP2 under ``ModelParallelStrategy`` (units from the backbone's ``shard_units``) and
        activation checkpointing. Runs after callbacks attached their objectives in ``setup``."""
        if self._parallelized:
            return
        self._warn_emulated_bf16()
        if self.frozen_dtype != torch.float32:
            self._check_autocast()
            cast_frozen_parameters(self.backbone, self.frozen_dtype, keep=self.float32_parameters)
            if self._pretrained is not None:
                reload_in_float32(self.backbone, self._pretrained, self.float32_parameters)
        parallelize(
            self.backbone,
            self.backbone.shard_units(),
            list(self.objectives.values()),
            self.device_mesh,
            self.activation_checkpointing,
        )
        self._parallelized = True

    def _warn_emulated_bf16(self) -> None:
        """bf16 on a CPU that emulates it is slower than float32, not faster: say so at the start."""
        if self._trainer is None or "bf16" not in str(self.trainer.precision):
            return
        if self.trainer.strategy.root_device.type == "cpu" and not native_bf16_cpu():
            warnings.warn(
                f"trainer.precision={self.trainer.precision} on a CPU without bf16 hardware (no "
                "AVX512-BF16 or AMX): torch emulates it, and openvla-oft-mini's training step took "
                "2.7x its float32 step on such a CPU (benchmarks/bench_mini.py). For speed, train "
                "with --trainer.precision=32-true --model.frozen_dtype=float32 (other numerics)",
                stacklevel=2,
            )

    def _check_autocast(self) -> None:
        precision = str(self.trainer.precision) if self._trainer is not None else None
        if precision not in (None, "bf16-mixed", "16-mixed"):
            raise BackboneError(
                f"model.frozen_dtype={dtype_name(self.frozen_dtype)} needs trainer.precision: "
                f"bf16-mixed (autocast), not {precision}: without it float32 activations meet "
                f"{dtype_name(self.frozen_dtype)} weights. Set both, or model.frozen_dtype=float32"
            )

    # -- objectives ----------------------------------------------------------------------------

    def add_objective(self, objective: Objective) -> None:
        """Attach a loss term (callbacks call this in ``setup``, before optimizers exist)."""
        if objective.name in self.objectives or objective.name == "action":
            raise ValueError(f"an objective named {objective.name!r} is already attached")
        self.objectives[objective.name] = objective

    def remove_objective(self, name: str) -> None:
        del self.objectives[name]

    def output_request(self) -> OutputRequest:
        request = OutputRequest()
        for objective in self.objectives.values():
            request = request.merged(objective.request)
        return request

    # -- steps ---------------------------------------------------------------------------------

    def forward(self, batch: Batch) -> Tensor:
        """(B, T, A) normalised actions."""
        return self.backbone(batch).actions

    def compute_losses(self, batch: Batch) -> dict[str, Tensor]:
        return compute_losses(self.backbone, self.objectives.values(), batch)

    def training_step(self, batch: Batch, batch_idx: int) -> Tensor:
        losses = self.compute_losses(batch)
        total = losses["action"]
        for name, objective in self.objectives.items():
            total = total + objective.weight * losses[name]
        self._stop_unless_finite(losses)
        batch_size = len(batch["instruction"])
        for name, value in losses.items():
            self.log(f"train/loss_{name}", value.detach(), batch_size=batch_size)
        self.log("train/loss", total.detach(), prog_bar=True, batch_size=batch_size)
        return total

    def _stop_unless_finite(self, losses: dict[str, Tensor]) -> None:
        """Stop the fit at its first non-finite loss, before backward lets it into the weights
        (a NaN loss trains every weight to NaN and the fit would go on and export them). Every
        rank decides together, so none waits in a collective for one that stopped."""
        bad = [name for name, value in losses.items() if not bool(value.detach().isfinite())]
        trainer = self._trainer
        if trainer is not None and trainer.world_size > 1:
            anywhere = trainer.strategy.reduce_boolean_decision(bool(bad), all=False)
        else:
            anywhere = bool(bad)
        if not anywhere:
            return
        step = self.global_step
        where = (
            ", ".join(f"{name} = {float(losses[name].detach())}" for name in bad)
            if bad
            else "on another rank"
        )
        raise CapVectorError(
            f"step {step}: loss term {where} is not finite; stopped before training on it. Look "
            "for NaN/inf in the data (e.g. depth or proprio) or lower the learning rate"
        )

    def on_fit_start(self) -> None:
        """Lightning warns of every module in eval mode at the start of training; a module that
        sets ``keeps_eval_mode`` stays so on purpose (the mini's frozen BatchNorm tower). When those
        are all there are, that warning (with their exact count) is replaced by one info line."""
        in_eval = [name for name, module in self.named_modules() if not module.training]
        kept = [name for name, m in self.named_modules() if getattr(m, "keeps_eval_mode", False)]
        if in_eval and all(any(n == k or n.startswith(k + ".") for k in kept) for n in in_eval):
            warnings.filterwarnings("ignore", rf"Found {len(in_eval)} module\(s\) in eval mode")
            rank_zero_info(
                f"{len(in_eval)} modules stay in eval mode on purpose, by design of "
                f"{', '.join(kept)} (keeps_eval_mode: frozen normalisation statistics)"
            )

    def setup(self, stage: str) -> None:
        datamodule = (
            getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        )
        for spec in EpisodeDataset(getattr(datamodule, "eval_tasks", None) or []).specs:
            key = _task_key(spec)
            if key not in self.success_rates:
                self.success_rates[key] = SuccessRate()
        if self.success_rates and "all" not in self.success_rates:
            self.success_rates["all"] = SuccessRate()

    def teardown(self, stage: str) -> None:
        if self.success_rates:  # rollouts ran: release the cached simulators and their GL contexts
            from capvector.eval.rollout import close_envs

            close_envs()

    def validation_step(self, batch: Any, batch_idx: int, dataloader_idx: int = 0) -> None:
        if is_episode_batch(batch):
            self._rollout(batch)
            return
        self.log(
            "val/action_l1", held_out_action_l1(self.backbone, batch), prog_bar=True,
            sync_dist=True, batch_size=len(batch["instruction"]), add_dataloader_idx=False,
        )  # fmt: skip

    def _rollout(self, items: list[EpisodeItem]) -> None:
        from capvector.eval.rollout import ProgressLines

        counted = [item for item in items if item.counted]  # the rest only evens out the ranks
        evaluator = self._evaluator()
        label = f"{VALIDATION_PROGRESS} {self.global_step}"
        if self.trainer.world_size > 1:
            label += " (rank 0's share)"  # what rank_zero_info shows
        results = evaluator.run(
            VLAPolicy(self.backbone, self.data_spec),
            [item.spec for item in counted],
            [item.index for item in counted],
            lines=ProgressLines(len(counted), label, rank_zero_info),
        )
        for result in results:  # the mp4s are written; the loggers people watch show them too
            if result.frames:
                path = evaluator.video_path(result)
                # At the step Lightning logs this validation's success rates with.
                log_video(self.loggers, f"val/video/{path.stem}", result.frames, path,
                          logging_step(self.trainer))  # fmt: skip
        for item, result in zip(counted, results, strict=True):
            made_by = suite_of(item.spec).provenance(item.spec)
            self._episode_rows.append([
                self.global_step, _task_key(item.spec), item.spec.seed, int(result.success),
                made_by.stack, made_by.renderer,
            ])  # fmt: skip
            self.episode_count.update(1.0)
            for key in (_task_key(item.spec), "all"):
                self.success_rates[key].update(result.success)
        # Logged once per rank, also when it had no counted episode: the reductions line up.
        self.log(
            "val/episodes", self.episode_count, on_epoch=True, batch_size=1, reduce_fx="sum",
            add_dataloader_idx=False,
        )  # fmt: skip
        for key, metric in self.success_rates.items():
            # Not val/success_rate/<key>: a name must not be a prefix folder of another (loggers.py).
            name = "val/success_rate" if key == "all" else f"{SUCCESS_BY_TASK}/{key}"
            self.log(
                name, metric, on_epoch=True, batch_size=1, add_dataloader_idx=False,
                prog_bar=key == "all",
            )  # fmt: skip

    def on_validation_epoch_start(self) -> None:
        root = run_folder(self.trainer)  # collective under DDP: every rank asks once, here
        self._video_dir = root / "videos" / f"step{self.global_step:06d}"
        rank = self.trainer.global_rank
        self._episodes_log = root / (
            EPISODES_LOG if rank == 0 else EPISODES_LOG.replace(".", f"_rank{rank}.")
        )
        self._episode_rows = []

    def on_validation_epoch_end(self) -> None:
        # Each rank appends the outcomes of its own episodes (the success metrics above are
        # their reduction); evaluations repeated after a resume appear twice, as in metrics.csv.
        if not self._episode_rows:
            return
        new = not self._episodes_log.exists()
        # A log begun before episodes said their stack (a resumed fit) keeps its four columns.
        labelled = new or "stack" in self._episodes_log.open().readline()
        self._episodes_log.parent.mkdir(parents=True, exist_ok=True)
        with self._episodes_log.open("a", newline="") as f:
            writer = csv.writer(f)
            if new:
                writer.writerow(EPISODE_COLUMNS)
            writer.writerows(row if labelled else row[:4] for row in self._episode_rows)
        self._episode_rows = []
        log_file(self.loggers, self._episodes_log)

    def _evaluator(self) -> Any:
        from capvector.eval.rollout import RolloutEvaluator

        spec = self.data_spec
        return RolloutEvaluator(
            cameras=spec.cameras,
            image_size=spec.image_size,
            camera_fovy=spec.camera_fovy,
            execute_steps=self.rollout.execute_steps,
            videos=self.rollout.videos,
            video_dir=self._video_dir,
            batch_size=self.rollout.batch_size,
            workers=self.rollout.workers,
        )

    # -- optimisation ------------------------------------------------------------------------

    def configure_optimizers(self) -> dict[str, Any]:
        settings = self.optimizer_settings
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = torch.optim.AdamW(
            params, lr=settings.lr, weight_decay=settings.weight_decay, betas=tuple(settings.betas)
        )
        total = max(1, self.trainer.max_steps) if self.trainer.max_steps > 0 else None
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _schedule(settings, total))
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }

    # -- persistence ---------------------------------------------------------------------------

    def checkpoint_metadata(self) -> CheckpointMetadata:
        """What tools outside Lightning need to read a checkpoint (``capvector.vectors``, eval)."""
        lora = self.lora_settings
        return CheckpointMetadata(
            family=self.backbone.config_class.family,
            backbone_config=self.backbone.config.to_dict(),
            capability_parameters=list(self.backbone.capability_parameters),
            embedding_parameters=self.backbone.embedding_parameter_names(),
            lora=None
            if lora is None
            else {"r": lora.r, "alpha": lora.alpha, "scaling": lora.scaling},
            data_spec=dataclasses.asdict(self.data_spec),
            objectives=sorted(self.objectives),
            merged_vectors=record_dicts(self.merged_vectors),
        )

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[CHECKPOINT_METADATA] = self.checkpoint_metadata().to_dict()
        # A base rebuilt from weight packages leaves its weights out of the state dict, and with
        # them the deltas they carry (θ_pre's LoRA): those travel beside it, as (B, A).
        deltas = self.backbone.base_delta
        if deltas:
            checkpoint[BASE_DELTA] = {k: {"B": b, "A": a} for k, (b, a) in deltas.items()}

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.merged_vectors = read_record(
            checkpoint.get(CHECKPOINT_METADATA, {}).get(MERGED_VECTORS)
        )
        # Before the state dict loads (Lightning and load_module both call this first): a model
        # rebuilt from the packages alone (load_module, or θ_pre's export gone) gets its deltas.
        deltas = checkpoint.get(BASE_DELTA)
        if deltas:
            self.backbone.set_base_delta({k: (v["B"], v["A"]) for k, v in deltas.items()})

    def export(self, folder: str | Path, overwrite: bool = False, dtype: str | None = None) -> Path:
        """An export folder: ``model.safetensors`` (LoRA merged) + config + statistics + tokenizer.

        Every floating tensor is written in ``dtype``, by default the base's: ``frozen_dtype``, as
        OpenVLA-OFT's merge script writes its LoRA fit (vla-scripts/merge_lora_weights_and_save.py
        loads the base with ``torch_dtype=torch.bfloat16``, merges, saves; its L1 action head is
        bf16 too, finetune.py ``init_module(..., to_bf16=True)``). A bf16-frozen ``pi05-3b`` LoRA
        fit so writes 6.7 GB, not 11 GB of mixed float32 and bf16. ``float32`` keeps what trained
        (LoRA-merged weights, heads) unrounded: a bf16 weight keeps about 3 significant digits,
        so an update smaller than 1/256 of a weight, as a short LoRA fit's, rounds away in bf16.

        Collective under FSDP2: every rank calls it, rank 0 gathers the full weights and writes.
        """
        out_dtype = self.frozen_dtype if dtype is None else parse_dtype(dtype)
        state = full_state_dict(self.backbone)
        if not is_rank_zero():
            return Path(folder)
        lora_settings = self.lora_settings
        base_delta = self.backbone.base_delta
        if base_delta is not None:
            # The base is rebuilt from weight packages: LoRA stays low-rank, stacked on the
            # deltas the base already carries (an export of what trains, not 135 MB of Gemma).
            scaling = constant_scaling(lora_settings.scaling if lora_settings else 1.0)
            state = lora_form_state(state, scaling, base_delta)
        elif lora_settings is not None:
            scaling = constant_scaling(lora_settings.scaling)
            state = merged_lora_view(state, scaling, dtype=out_dtype)
        has_delta = any(".lora_" in k for k in state) and base_delta is not None
        # Made one at a time as they are written: a 7 B export never holds a second copy.
        tensors = LazyTensors()
        for name in state:
            info = tensor_info(state, name)
            # Low-rank factors (the base-delta form) have no base dtype: float32 unless asked.
            keep = not info.dtype.is_floating_point or (dtype is None and ".lora_" in name)
            out = info if keep else TensorInfo(out_dtype, info.shape)
            tensors.set(
                name, out, lambda n=name, d=out.dtype: _finite_export_tensor(state, n, d, folder)
            )
        extra = {
            DATA_SPEC_FILE: dataclasses.asdict(self.data_spec),
            STATISTICS_FILE: self.data_spec.statistics,
        }
        return self.backbone.save_pretrained(
            folder,
            state_dict=tensors,
            extra_json=extra,
            config_extra={
                "objectives": sorted(self.objectives),
                MERGED_VECTORS: record_dicts(self.merged_vectors),
                "frozen_dtype": dtype_name(self.frozen_dtype),
                **({BASE_DELTA: {"form": "lora", "scaling": 1.0}} if has_delta else {}),
                # Of every floating tensor written; the key transformers' config.json uses.
                "torch_dtype": dtype_name(out_dtype),
            },
            overwrite=overwrite,
            card_facts={
                "training steps": self.trainer.global_step if self._trainer else None,
                "objectives": sorted(self.objectives),
                "LoRA": None if lora_settings is None else dataclasses.asdict(lora_settings),
                "merged vectors": [m.describe() for m in self.merged_vectors],
                "datasets": sorted(self.data_spec.statistics),
            },
            base_model=self.hparams.get("pretrained"),
            inputs=[self.hparams.get("pretrained")],
        )


def _finite_export_tensor(
    state: Mapping[str, Tensor], name: str, dtype: torch.dtype, folder: str | Path
) -> Tensor:
    tensor = state[name].to(dtype)
    # A policy that answers NaN must not leave here (float16 can overflow too). Raised while the
    # export writes into its temporary folder, which is then removed: nothing is left behind.
    if tensor.is_floating_point() and not all_finite(tensor):
        raise CapVectorError(
            f"not exporting to {folder}: `{name}` holds NaN or inf in {dtype_name(dtype)}; train "
            "from a finite checkpoint (a fit stops at its first non-finite loss), or export in "
            "float32 (--dtype float32)"
        )
    return tensor


T = TypeVar("T")

DEFAULT_PRESET = "openvla-oft-tiny"
"""What ``capvector fit`` trains when neither ``model.backbone`` nor ``model.pretrained`` is set."""


def held_out_action_l1(backbone: VLABackbone, batch: Batch) -> Tensor:
    """Mean L1 between the predicted and the target actions (normalised space).

    For an L1 head this is its loss; for a flow-matching head it is the L1 of the actions its
    sampler produces (the ones a rollout would execute), not its velocity loss. Pi0.5 returns its
    one-step denoised estimate with targets (``Pi05.forward``): a cheap stand-in for sampling.
    """
    output = backbone(batch, OutputRequest(actions=True))
    target = batch["actions"]
    return torch.nn.functional.l1_loss(
        output.actions.float(), target.to(output.actions.device).float()
    )


def _folder_data_spec(folder: Path) -> dict[str, Any]:
    spec_file = folder / DATA_SPEC_FILE
    if not spec_file.is_file():
        raise BackboneError(f"{folder} has no {DATA_SPEC_FILE}: export it with capvector")
    return read_json(spec_file)


def load_for_inference(
    checkpoint: str | Path, keep_dtype: bool = False
) -> tuple[VLABackbone, DataSpec]:
    """The backbone (in eval mode, nothing trains) and data spec of a checkpoint or an export
    folder, as ``capvector evaluate`` and ``serve`` run them.

    ``keep_dtype``: an export's weights stay in the dtype it was written in (its ``torch_dtype``)
    instead of float32, loaded tensor by tensor. For inference under autocast, where a float32
    copy of a bf16 export is twice the memory for nothing (pi05-3b: 13 GB instead of 6.4 GB); a
    Lightning checkpoint loads as ``load_module`` loads it."""
    folder = local_folder(checkpoint, "checkpoint")
    if keep_dtype and folder.is_dir():
        spec = _as(DataSpec, _folder_data_spec(folder))
        assert spec is not None
        dtype = frozen_dtype_of(load_export_config(folder).get("torch_dtype", "float32"))
        backbone = load_pretrained(str(checkpoint), dtype, lambda m: m.requires_grad_(False))
        return backbone.eval(), spec
    module = load_module(checkpoint)
    return module.backbone.eval(), module.data_spec


def _export_data_spec(folder: str) -> dict[str, Any] | None:
    """The data spec an export was trained with (None for one without, e.g. an import)."""
    path = local_folder(folder, "model.pretrained") / DATA_SPEC_FILE
    return read_json(path) if path.is_file() else None


def _as(cls: type[T], value: T | Mapping[str, Any] | None) -> T | None:
    return cls(**value) if isinstance(value, Mapping) else value


def _task_key(spec: Spec) -> str:
    return metric_key(spec.task, spec.robot, spec.variant)


def _schedule(settings: OptimizerSettings, total_steps: int | None) -> Any:
    kind = settings.schedule
    if kind not in ("constant", "cosine", "step"):
        raise CapVectorError(f"unknown lr schedule {kind!r}; use constant, cosine or step")
    if kind == "cosine" and total_steps is None:
        raise CapVectorError("the cosine schedule needs trainer.max_steps")

    def factor(step: int) -> float:
        if step < settings.warmup_steps:
            return (step + 1) / settings.warmup_steps
        if kind == "step":
            return settings.decay_factor ** sum(step >= s for s in settings.decay_steps)
        if kind == "cosine":
            progress = min(
                1.0, (step - settings.warmup_steps) / max(1, total_steps - settings.warmup_steps)
            )
            floor = settings.min_lr_ratio
            return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))
        return 1.0

    return factor


def load_module(checkpoint: str | Path, map_location: str = "cpu") -> VLAModule:
    """A trained module from a Lightning checkpoint or an export folder (a local one, or a hub
    id's snapshot; objectives, which are training-only, are dropped)."""
    folder = local_folder(checkpoint, "checkpoint")
    if folder.is_dir():  # a hub id stays the module's `pretrained`: its exports name it as base
        return VLAModule(pretrained=str(checkpoint), data_spec=_folder_data_spec(folder))
    if not Path(checkpoint).is_file():
        raise BackboneError(f"checkpoint {checkpoint} does not exist")
    ckpt = load_torch(checkpoint, map_location=map_location, weights_only=False)
    meta = CheckpointMetadata.from_checkpoint(ckpt, str(checkpoint))
    accepted = inspect.signature(VLAModule.__init__).parameters
    # LightningCLI adds bookkeeping entries (`_instantiator`, `_class_path`) to the hparams.
    hparams = {k: v for k, v in ckpt.get("hyper_parameters", {}).items() if k in accepted}
    backbone_class(meta.family, meta.backbone_config.get("preset"))  # clear error if unknown
    # The checkpoint holds every weight and the resolved architecture: the θ_pre folder it started
    # from may be gone, so rebuild from the saved config instead of from `pretrained`.
    hparams["pretrained"] = None
    hparams["backbone"] = meta.backbone_config["preset"]
    hparams["backbone_overrides"] = dict(meta.backbone_config)
    module = VLAModule(**hparams)
    module.on_load_checkpoint(ckpt)
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith("objectives.")}
    missing, unexpected = module.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise BackboneError(
            f"{checkpoint} does not fit: missing {missing[:3]}, unexpected {unexpected[:3]}"
        )
    return module
