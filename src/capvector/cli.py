"""``capvector``: LightningCLI for training (fit/validate/test) plus the recipe's tools.

Training subcommands go to LightningCLI (YAML configs, omegaconf interpolation). Tool subcommands
are looked up in ``TOOLS`` and imported only when called, so ``capvector extract`` does not pay for
importing the simulator and ``capvector fit`` does not pay for the vector tools.
"""

from __future__ import annotations

import errno
import importlib
import os
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from capvector.errors import CapVectorError, ToolParser, config_error
from capvector.io.outputs import check_output

if TYPE_CHECKING:
    from capvector.backbones import VLABackbone

LIGHTNING_SUBCOMMANDS = ("fit", "validate", "test", "predict")

TOOLS: dict[str, tuple[str, str]] = {  # name: ("module:function", help), imported when called
    "backbone-info": ("capvector.cli:backbone_info_main", "parameter counts of a preset"),
    "export": ("capvector.cli:export_main", "export a checkpoint to a safetensors folder"),
    "import-original": ("capvector.cli:import_original_main", "original checkpoint -> export"),
    "demos": ("capvector.sim.demos:main", "record scripted robosuite demonstrations"),
    "evaluate": ("capvector.workflows.evaluate:main", "MuJoCo rollouts of a checkpoint"),
    "recipe": ("capvector.workflows.recipe:main", "run the whole recipe as resumable stages"),
    "sweep-scale": ("capvector.workflows.sweep:main", "choose the merge scale λ"),
    "extract": ("capvector.vectors.cli:extract_main", "capability vector = aux - sft"),
    "merge": ("capvector.vectors.cli:merge_main", "base + sum of scaled vectors"),
    "compose": ("capvector.vectors.cli:compose_main", "combine vectors (sum, TIES)"),
    "inspect": ("capvector.vectors.cli:inspect_main", "norms, cosines and plots of vectors"),
    "report": ("capvector.workflows.report:main", "success vs steps of a recipe's arms"),
    "serve": ("capvector.serve.cli:main", "answer observations over openpi's websocket protocol"),
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Its bad input (a ``CapVectorError`` raised anywhere, or an environment
    failure such as a full disk) is printed here as one line, for every command alike; anything
    else is a bug and keeps its traceback."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(_usage())
        return 0
    command, rest = args[0], args[1:]
    if command not in LIGHTNING_SUBCOMMANDS and command not in TOOLS:
        print(f"capvector: unknown command {command!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        if command in LIGHTNING_SUBCOMMANDS:
            # From a shell, LightningCLI reads sys.argv itself (it warns when given both).
            run_lightning_cli(None if argv is None else [command, *rest])
            return 0
        module, function = TOOLS[command][0].split(":")
        tool: Callable[[list[str]], int] = getattr(importlib.import_module(module), function)
        with _terminate_as_exit():
            return int(tool(rest) or 0)
    except KeyboardInterrupt:  # outputs are written atomically: an interrupted one is not there
        print(f"capvector {command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        error, code = _reported(exc)
        if error is None:
            raise
        print(f"capvector {command}: error: {error}", file=sys.stderr)
        return code


ENVIRONMENT_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM})
"""OSErrors that are the machine refusing (full disk, quota, read-only, permissions), not a bug."""


def _reported(exc: BaseException) -> tuple[BaseException | None, int]:
    """The error to print as one line and the exit code: bad input (exit 2), ours or ours wrapped
    (jsonargparse re-raises an error of a link's compute_fn, e.g. the data module's spec, as a
    ValueError caused by it), or the environment refusing (exit 1); ``None`` for a bug."""
    cause: BaseException | None = exc
    while cause is not None:
        if isinstance(cause, CapVectorError | FileExistsError):
            return cause, 2
        cause = cause.__cause__
    if isinstance(exc, OSError) and exc.errno in ENVIRONMENT_ERRORS:
        return exc, 1
    return None, 0


@contextmanager
def _terminate_as_exit() -> Iterator[None]:
    """SIGTERM (``kill``, a scheduler's time limit) ends a tool as Ctrl-C does, by an exception, so
    the outputs' cleanup runs and removes their temporary folders; by default it ended the process
    on the spot and left them behind. (LightningCLI has its own SIGTERM handling.)"""

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = signal.getsignal(signal.SIGTERM)
    # Only the main thread may set handlers; called from another thread, leave signals alone.
    install = threading.current_thread() is threading.main_thread() and previous is not None
    if install:
        signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        if install:
            signal.signal(signal.SIGTERM, previous)


def _usage() -> str:
    lines = ["usage: capvector COMMAND [...]", "", "training (LightningCLI, --config FILE.yaml):"]
    lines += [f"  {c}" for c in LIGHTNING_SUBCOMMANDS]
    lines += ["", "tools:"]
    lines += [f"  {name:<16} {help_}" for name, (_, help_) in TOOLS.items()]
    lines += ["", "Run `capvector COMMAND --help` for a command's options."]
    return "\n".join(lines)


def run_lightning_cli(args: list[str] | None) -> object:
    from argparse import ArgumentError

    from jsonargparse import Namespace
    from lightning.pytorch.cli import LightningCLI, SaveConfigCallback
    from omegaconf.errors import OmegaConfBaseException

    from capvector.data.datamodule import RobotDataModule
    from capvector.module import VLAModule

    class CapVectorCLI(LightningCLI):
        def parse_arguments(self, parser, args) -> None:  # noqa: ANN001 (Lightning's)
            from capvector.training.resume import check_ckpt_path

            super().parse_arguments(parser, args)
            # LightningCLI reads a given checkpoint's hyperparameters right after parsing.
            check_ckpt_path(self.config[self.config["subcommand"]].get("ckpt_path"))

        def add_arguments_to_parser(self, parser) -> None:  # noqa: ANN001 (jsonargparse parser)
            # Shapes, camera order and statistics come from the data, never typed twice.
            parser.link_arguments(
                "data", "model.data_spec", apply_on="instantiate", compute_fn=lambda dm: dm.spec
            )

        def before_instantiate_classes(self) -> None:
            # Lightning's default logger makes its version folder when the trainer sets up, so a
            # fit refused in setup left an empty run folder; ours (same layout) waits for a write.
            config = self.config[self.subcommand] if self.subcommand else self.config
            trainer = config.trainer
            if trainer.logger in (None, True):
                trainer.logger = Namespace(
                    class_path="capvector.training.loggers.CSVLogger",
                    init_args=Namespace(
                        save_dir=trainer.default_root_dir or os.getcwd(), name="lightning_logs"
                    ),
                )
            if config.data.get("generate"):
                _check_before_recording(config)

        def before_fit(self) -> None:
            from capvector.training.resume import (
                check_ckpt_path,
                check_fit_outputs,
                resume_latest_run,
            )

            check_fit_outputs(self.trainer)
            settings = self.config_init[self.subcommand]
            if settings.get("ckpt_path") == "last":
                settings["ckpt_path"] = str(resume_latest_run(self.trainer))
                print(f"capvector fit: resuming {settings['ckpt_path']}")
                check_ckpt_path(settings["ckpt_path"])

    class SaveConfigAtFitStart(SaveConfigCallback):
        """Lightning writes ``config.yaml`` into the run folder in ``setup``, before the module's
        ``setup`` and ``configure_model`` (e.g. ``model.frozen_dtype`` without autocast) and the
        callbacks' checks have run: a fit refused there left a run folder holding only the
        config. A fit saves it at ``on_fit_start``, once every check has passed."""

        def setup(self, trainer, pl_module, stage: str) -> None:  # noqa: ANN001 (Lightning's)
            if stage != "fit":
                super().setup(trainer, pl_module, stage)

        def on_fit_start(self, trainer, pl_module) -> None:  # noqa: ANN001 (Lightning's)
            super().setup(trainer, pl_module, "fit")

    subcommand = (args or sys.argv[1:])[0]
    try:
        return CapVectorCLI(
            VLAModule,
            RobotDataModule,
            args=args,
            # jsonargparse's own handler prints the whole usage block (~75 lines) before a typo'd
            # key; without exit_on_error it raises, and the error is the one line `main` prints.
            parser_kwargs={"parser_mode": "omegaconf", "exit_on_error": False},
            save_config_callback=SaveConfigAtFitStart,
            save_config_kwargs={"overwrite": True},
        )
    except ArgumentError as err:  # the command line, a config file, a checkpoint's hparams
        raise CapVectorError(f"{err} (see capvector {subcommand} --help)") from err
    except OmegaConfBaseException as err:  # an interpolation in a config file
        raise config_error(f"a {subcommand} config", err) from err


def _check_before_recording(config: object) -> None:
    """``data.generate`` records demos (minutes) when the CLI builds the data module: before the
    model, the trainer and ``before_fit``'s output checks. What the config alone can tell is
    checked first, so a typo does not cost a recording."""
    from capvector.backbones import preset_config
    from capvector.io.outputs import check_writable

    model, trainer = config.model, config.trainer  # type: ignore[attr-defined]
    if not model.get("pretrained"):
        preset_config(model.backbone)  # an unknown preset, with close names
    loggers = trainer.logger if isinstance(trainer.logger, list) else [trainer.logger]
    paths = [("trainer.default_root_dir", trainer.default_root_dir or os.getcwd())]
    for logger in loggers:
        save_dir = (logger.get("init_args") or {}).get("save_dir") if logger else None
        if save_dir:
            paths.append((f"the logger's save_dir ({logger.class_path})", save_dir))
    for what, path in paths:
        check_writable(path, f"into {what}", inside=True)


def backbone_info_main(argv: list[str]) -> int:
    """Parameter counts per component from a meta-device build (no memory, no download); with
    --memory the per-device training memory, with --flops the training FLOPs and GPU-hours."""
    import torch

    from capvector.backbones import build_backbone, list_presets
    from capvector.profiling.memory import ATTENTION_PATHS, FROZEN_DTYPES, PRECISIONS, STRATEGIES

    parser = ToolParser(prog="capvector backbone-info", description=backbone_info_main.__doc__)
    parser.add_argument("preset", nargs="?", help="a registered preset; omit with --list")
    parser.add_argument("--list", action="store_true", help="list the registered presets")
    parser.add_argument("--memory", action="store_true", help="estimate per-device training memory")
    parser.add_argument("--flops", action="store_true", help="training FLOPs per sample, GPU-hours")
    parser.add_argument("--batch", type=int, default=8, help="per-device batch size")
    parser.add_argument("--precision", default="bf16-mixed", choices=PRECISIONS)
    parser.add_argument("--strategy", default="fsdp2", choices=STRATEGIES)
    parser.add_argument("--devices", type=int, default=1, help="devices the model is sharded over")
    parser.add_argument("--lora-rank", type=int, default=None, help="train LoRA of this rank")
    parser.add_argument(
        "--frozen-dtype",
        default="float32",
        choices=list(FROZEN_DTYPES),
        help="storage dtype of the parameters that do not train (model.frozen_dtype)",
    )
    parser.add_argument(
        "--attention",
        default="efficient",
        choices=ATTENTION_PATHS,
        help="SDPA as a GPU runs it (efficient/flash kernels: no S x S attention matrix kept) or "
        "the math path (what the meta device and some CPUs take)",
    )
    parser.add_argument(
        "--activation-checkpointing",
        action="store_true",
        help="the total assumes model.activation_checkpointing: true",
    )
    parser.add_argument("--steps", type=int, default=100_000, help="optimizer steps (--flops)")
    parser.add_argument("--mfu", type=float, default=0.4, help="model FLOPs utilisation (--flops)")
    parser.add_argument(
        "--gpu-tflops", type=float, default=989.0, help="peak dense TFLOP/s (H100 bf16: 989)"
    )
    args = parser.parse_args(argv)
    if args.list or not args.preset:
        print("\n".join(list_presets()))
        return 0
    with torch.device("meta"):
        model = build_backbone(args.preset)
    print(f"{args.preset} ({type(model).__name__})")
    rows = [
        (name, sum(p.numel() for p in child.parameters())) for name, child in model.named_children()
    ]
    capability = set(model.capability_parameter_names())
    in_vector = sum(p.numel() for n, p in model.named_parameters() if n in capability)
    total = sum(count for _, count in rows)
    width = max(len(name) for name, _ in rows)
    for name, count in rows:
        print(f"  {name:<{width}}  {count:>15,}")
    print(f"  {'total':<{width}}  {total:>15,}")
    print(f"  {'capability':<{width}}  {in_vector:>15,}  (parameters a capability vector covers)")
    if args.memory:
        from capvector.profiling.memory import describe, estimate_memory

        settings = {
            "batch_size": args.batch, "precision": args.precision, "strategy": args.strategy,
            "devices": args.devices, "lora_rank": args.lora_rank,
            "frozen_dtype": args.frozen_dtype, "attention": args.attention,
            "activation_checkpointing": args.activation_checkpointing,
        }  # fmt: skip
        print(describe(estimate_memory(args.preset, **settings), **settings))
    if args.flops:
        from capvector.profiling.flops import estimate_flops

        flops = estimate_flops(args.preset, batch_size=args.batch, lora_rank=args.lora_rank)
        print(
            flops.table(
                steps=args.steps, batch_size=args.batch, devices=args.devices, mfu=args.mfu,
                gpu_tflops=args.gpu_tflops,
            )
        )  # fmt: skip
    return 0


def export_main(argv: list[str]) -> int:
    """Export a Lightning checkpoint to a folder that `extract`, `merge` and `evaluate` read."""
    from capvector.module import load_module

    parser = ToolParser(prog="capvector export", description=export_main.__doc__)
    parser.add_argument("--ckpt", required=True, help="Lightning checkpoint (.ckpt)")
    parser.add_argument("--out", required=True, help="output folder (written atomically)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    check_output(args.out, args.overwrite, [args.ckpt])  # before loading the checkpoint
    folder = load_module(args.ckpt).export(args.out, overwrite=args.overwrite)
    print(f"exported {args.ckpt} to {folder}")
    return 0


def import_original_main(argv: list[str]) -> int:
    """Convert an original project's checkpoint (OpenVLA-OFT run folder, LeRobot pi05 policy folder,
    StarVLA checkpoint + Qwen folder) into an export folder usable as ``--model.pretrained`` (θ_pre).
    The architecture comes from the checkpoint's own config files; statistics are always written.
    Each family adds its own options (below, by family; ``--preset P --help`` shows P's)."""
    import json

    from capvector.backbones import backbone_class, preset_config
    from capvector.backbones.base import registered_families

    parser = ToolParser(prog="capvector import-original", description=import_original_main.__doc__)
    parser.add_argument(
        "--preset", required=True, help="the architecture, e.g. openvla-oft-7b, pi05-3b"
    )
    parser.add_argument(
        "--folder", required=True, help="original checkpoint folder (or StarVLA checkpoint file)"
    )
    parser.add_argument("--out", required=True, help="export folder to write (atomically)")
    parser.add_argument(
        "--override",
        default="{}",
        help='JSON of config fields to change, e.g. \'{"featurizer": {"depth": 2}}\' (a nested '
        "object changes only the fields it names)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    # The family's own options (VLABackbone.import_options): the preset's family only, or every
    # registered family's when no preset is given (for --help).
    peek = ToolParser(prog=parser.prog, add_help=False)
    peek.add_argument("--preset")
    preset = peek.parse_known_args(argv)[0].preset
    family = None if preset is None else preset_config(preset).family
    families = registered_families() if family is None else {family: backbone_class(family)}
    _add_import_options(parser, families)
    args = parser.parse_args(argv)
    try:
        overrides = json.loads(args.override)
    except json.JSONDecodeError as exc:
        raise CapVectorError(f"--override is not JSON ({exc}): {args.override!r}") from exc
    if not isinstance(overrides, dict):
        raise CapVectorError(f"--override must be a JSON object, got {args.override!r}")
    cls = families[family]
    options = {o.name: getattr(args, o.name) for o in cls.import_options if o.name in args}
    # The family's Path options name files the import reads: the output must stay clear of them.
    inputs = [args.folder, *(options.get(o.name) for o in cls.import_options if o.type is Path)]
    check_output(args.out, args.overwrite, inputs)  # before reading the checkpoint
    imported = cls.from_original(args.folder, preset=args.preset, overrides=overrides, **options)
    imported.model.save_pretrained(
        args.out,
        extra_json={"dataset_statistics.json": imported.statistics},
        overwrite=args.overwrite,
        card_facts={
            "imported from": str(Path(args.folder).resolve()),
            "command": shlex.join(["capvector", "import-original", *argv]),
        },
        base_model=str(args.folder),
        inputs=inputs,
    )
    n_params = sum(p.numel() for p in imported.model.parameters())
    print(f"wrote {args.out} ({family}, {n_params:,} parameters)")
    return 0


def _add_import_options(parser: ToolParser, families: Mapping[str, type[VLABackbone]]) -> None:
    """One argument group per family with its ``import_options``; an option two families declare
    is one flag whose help names both. Absent options are left out of the parsed namespace, so
    the loader's own defaults apply."""
    import argparse

    from capvector.backbones import BackboneError

    added: dict[str, argparse.Action] = {}
    for family, cls in families.items():
        if not cls.import_options:
            continue
        group = parser.add_argument_group(f"options of {family} presets")
        for option in cls.import_options:
            flag = "--" + option.name.replace("_", "-")
            if flag in added:
                added[flag].help = f"{added[flag].help}; {family}: {option.help}"
                continue
            kind = {"action": "store_true"} if option.type is bool else {"type": option.type}
            try:
                added[flag] = group.add_argument(
                    flag, dest=option.name, default=argparse.SUPPRESS, help=option.help, **kind
                )
            except argparse.ArgumentError as err:
                raise BackboneError(
                    f"{cls.__name__}.import_options: {err}; rename the option"
                ) from err


if __name__ == "__main__":
    sys.exit(main())
