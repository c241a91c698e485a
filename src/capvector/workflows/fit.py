"""``capvector fit``/``validate``/``test``/``predict``: LightningCLI over ``VLAModule`` and
``RobotDataModule``, and the parsed fit config other workflows build from (``capvector
sweep-scale``)."""

from __future__ import annotations

import os
import re
import signal
import sys
from typing import Any

from capvector.errors import CapVectorError, config_error
from capvector.io.names import STAGE_CORES

CSV_LOGGER = "capvector.training.loggers.CSVLogger"


def run_lightning_cli(args: list[str] | None, run: bool = True) -> object:
    """``capvector fit``/``validate``. With ``run=False``, ``args`` are a fit's options without
    the subcommand, only parsed: the returned CLI's ``parser`` and ``config`` build the model,
    data module and trainer settings when the caller asks
    (``cli.parser.instantiate_classes(cli.config)``; ``capvector sweep-scale``, once per λ)."""
    from argparse import ArgumentError

    from jsonargparse import Namespace
    from lightning.pytorch.cli import LightningCLI, SaveConfigCallback
    from lightning.pytorch.utilities.exceptions import SIGTERMException
    from omegaconf.errors import OmegaConfBaseException

    from capvector.data.datamodule import RobotDataModule
    from capvector.module import VLAModule

    class CapVectorCLI(LightningCLI):
        def parse_arguments(self, parser, args) -> None:  # noqa: ANN001 (Lightning's)
            from capvector.training.resume import check_ckpt_path

            super().parse_arguments(parser, args)
            if run:  # LightningCLI reads a given checkpoint's hyperparameters right after parsing.
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
                    class_path=CSV_LOGGER,
                    init_args=Namespace(
                        save_dir=trainer.default_root_dir or os.getcwd(), name="lightning_logs"
                    ),
                )
            elif isinstance(trainer.logger, list):
                trainer.logger = csv_logger_first(trainer.logger)
            if config.data.get("normalization") is None:
                config.data.normalization = family_config(config.model).normalization
            if config.data.get("generate"):
                _check_before_recording(config)

        def instantiate_classes(self) -> None:
            if run:  # otherwise the caller instantiates, as often as it needs
                super().instantiate_classes()

        def before_fit(self) -> None:
            from capvector.training.resume import (
                check_ckpt_path,
                check_fit_outputs,
                resume_latest_run,
            )

            check_fit_outputs(
                self.trainer, self.model, fit_inputs(self.model, self.datamodule, self.trainer)
            )
            if not (os.environ.get("OMP_NUM_THREADS") or os.environ.get(STAGE_CORES)):
                # Started by hand: share the cores with the other fits running (the callback's
                # docstring says why); a recipe stage or the user fixed the threads otherwise.
                from capvector.callbacks import ShareCores

                self.trainer.callbacks.append(ShareCores())
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
            # SaveConfigCallback.setup's write, into the run folder rather than trainer.log_dir:
            # with MLflow as the first logger that is its store's root, which MLflow then reports
            # as a malformed experiment (run_folder says where instead).
            from capvector.training.loggers import run_folder

            folder = run_folder(trainer)  # collective: every rank asks
            if trainer.is_global_zero and not self.already_saved:
                folder.mkdir(parents=True, exist_ok=True)
                self.parser.save(
                    self.config, str(folder / self.config_filename), skip_none=False,
                    overwrite=self.overwrite, multifile=self.multifile,
                )  # fmt: skip
                self.save_config(trainer, pl_module, "fit")
            self.already_saved = True

    subcommand = (args or sys.argv[1:])[0] if run else "fit"
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
            run=run,
        )
    except ArgumentError as err:  # the command line, a config file, a checkpoint's hparams
        raise CapVectorError(
            f"{parse_error_line(str(err))} (see capvector {subcommand} --help)"
        ) from err
    except OmegaConfBaseException as err:  # an interpolation in a config file
        raise config_error(f"a {subcommand} config", err) from err
    except SIGTERMException as stop:
        # Lightning ends a SIGTERMed run (a `kill`, a scheduler's preemption or time limit) by a
        # bare SystemExit, i.e. exit status 0, as if it had finished: a recipe stage would count
        # as done. It ends here as a process killed by SIGTERM does.
        print(f"capvector {subcommand}: stopped by SIGTERM before its end", file=sys.stderr)
        raise SystemExit(128 + signal.SIGTERM) from stop


def family_config(model: Any) -> type:
    """The config class of the backbone family a fit's ``model`` settings build: its preset's, or
    the ``pretrained`` export's, or the default preset's (``VLAModule``'s rule)."""
    from capvector.backbones import preset_config
    from capvector.backbones.base import backbone_class, load_export_config
    from capvector.module import DEFAULT_PRESET

    if model.get("backbone"):
        return type(preset_config(model.backbone))
    if model.get("pretrained"):
        return backbone_class(load_export_config(model.pretrained)["family"]).config_class
    return type(preset_config(DEFAULT_PRESET))


def parse_error_line(message: str) -> str:
    """jsonargparse's error for a value of the wrong type, 2 to 12 lines (``Parser key "K":``,
    the union's subtypes, each subtype's error, nested again for a callback's init argument), as
    one line naming the key, the value and the expected type: ``data.batch_size is 'four';
    expected int``. Other errors (an unknown key) are their lines joined."""
    lines = [line.strip() for line in message.strip().splitlines() if line.strip()]
    joined = " ".join(lines)
    key = re.match(r'Parser key "([^"]+)":', joined)
    if key is None:
        return joined
    name, owner = key[1], ""
    nested = re.search(
        r"Problem with given class_path '([\w.]+)': Parser key \"([^\"]+)\":", joined
    )
    if nested:  # a class's init argument: the first class tried is the one given
        name, owner = f"{name}.{nested[2]}", f" ({nested[1].rpartition('.')[2]})"
        joined = joined[nested.end() :]
    subtypes = re.search(r"Subtypes: \[(.*?)\] Errors:", joined)
    expected = re.search(r"Expected a (<class '[\w.]+'>|\S+)\.? Got value: (.*?)(?: - |$)", joined)
    given = re.search(r"Given value: (.*)$", joined)
    if subtypes and given:
        kinds, value = _type_names(subtypes[1]), given[1]
    elif expected:
        kinds, value = _type_names(expected[1]), expected[2]
    else:
        return joined
    if kinds == "float" and value.strip().lower().lstrip("+-") in ("nan", "inf", "infinity"):
        return f"{name}{owner} is {value}, which is not finite; expected a finite float"
    return f"{name}{owner} is {value!r}; expected {kinds}"


def _type_names(types: str) -> str:
    """``[<class 'int'>, <class 'NoneType'>]`` as ``int or None``."""
    names = [n.rpartition(".")[2] for n in re.findall(r"<class '([\w.]+)'>", types)] or [types]
    return " or ".join("None" if n == "NoneType" else n for n in names)


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


def fit_inputs(model: object, datamodule: object, trainer: object) -> list[str]:
    """The local paths a fit reads: the pretrained export, the demos, merged vectors' folders."""
    hparams = getattr(model, "hparams", {})
    data = getattr(datamodule, "hparams", {})
    paths = [hparams.get("pretrained"), data.get("lerobot_root")]
    paths += [*(data.get("train_files") or []), *(data.get("val_files") or [])]
    for callback in getattr(trainer, "callbacks", None) or []:
        paths.append(getattr(callback, "vector", None))  # MergeCapabilityVector's folder
    # A hub id is no local path; a demo file `data.generate` has yet to record is not there yet.
    return [str(p) for p in paths if isinstance(p, str | os.PathLike) and os.path.exists(p)]


def csv_logger_first(loggers: list) -> list:
    """The fit's loggers with capvector's CSV logger first, and only the last one given of it.

    Lightning puts checkpoints, and this project the export, rollout videos and ``episodes.csv``,
    into the first logger's folder, so they land beside ``metrics.csv`` whatever the order of the
    loggers. A CSV logger given later (``--trainer.logger+=``, as ``capvector recipe`` adds its
    own to a config's loggers) replaces a config's: a fit keeps one ``metrics.csv``."""
    ours = [logger for logger in loggers if logger and logger.class_path == CSV_LOGGER]
    if not ours:
        return loggers
    return [ours[-1], *(logger for logger in loggers if logger not in ours)]
