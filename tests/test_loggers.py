"""The CSV logger keeps a resumed fit's earlier metrics (Lightning's deletes them)."""

from __future__ import annotations

import csv
from pathlib import Path

from lightning.pytorch.loggers import CSVLogger as LightningCSVLogger

from capvector.training.loggers import CSVLogger


def rows(logger: LightningCSVLogger) -> list[dict[str, str]]:
    with open(Path(logger.log_dir) / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_second_run_in_the_same_folder_appends_with_the_earlier_columns(tmp_path: Path) -> None:
    first = CSVLogger(tmp_path, name="fit", version="version_0")
    first.log_metrics({"train/loss": 1.0}, step=0)
    first.log_metrics({"val/success_rate": 0.5}, step=1)
    first.save()
    resumed = CSVLogger(tmp_path, name="fit", version="version_0")  # a resumed fit, same folder
    resumed.log_metrics({"train/loss": 0.5, "perf/step_seconds": 0.1}, step=1)
    resumed.save()
    got = rows(resumed)
    assert [r["step"] for r in got] == ["0", "1", "1"]
    assert got[0]["train/loss"] == "1.0" and got[1]["val/success_rate"] == "0.5"
    assert got[2]["train/loss"] == "0.5" and got[2]["perf/step_seconds"] == "0.1"

    # Lightning's own logger, for contrast: the earlier rows are gone.
    lightning = LightningCSVLogger(tmp_path, name="fit", version="version_0")
    lightning.log_metrics({"train/loss": 0.25}, step=2)
    lightning.save()
    assert [r["step"] for r in rows(lightning)] == ["2"]
