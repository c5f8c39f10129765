"""One logger interface over wandb (offline by default), CSV, or nothing."""
from __future__ import annotations

import csv
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LOGGERS = ("wandb", "csv", "none")
log = logging.getLogger("topocut")


def wandb_location(run, mode: str) -> str:
    """One line on where a wandb run goes: its offline directory (and how to upload it) or its page; "" when
    disabled."""
    if mode == "disabled" or getattr(run, "disabled", False):
        return ""
    if mode == "offline" or getattr(run, "offline", False):
        where = run.settings.sync_dir
        return f"wandb: offline run written to {where} (upload it with `wandb sync {where}`)"
    return f"wandb: run {run.url}"


@dataclass
class LoggerConfig:
    kind: str = "wandb"  # wandb | csv | none
    project: str = "topocut"
    mode: str = "offline"  # wandb mode: offline | online | disabled
    entity: str | None = None


class RunLogger:
    """``log(metrics, step)``, ``log_image(key, path)``, ``lightning()`` and ``finish()``."""

    def __init__(self, kind: str, run_dir: Path, name: str, config: dict | None = None,
                 project: str = "topocut", mode: str = "offline", entity: str | None = None):
        if kind not in LOGGERS:
            raise ValueError(f"logger={kind!r} is not valid; choose one of {', '.join(LOGGERS)}")
        self.kind, self.run_dir, self.name = kind, Path(run_dir), name
        self.project, self.mode, self.entity = project, mode, entity
        self._wandb = None
        self.where = ""  # wandb: where the run went (wandb_location)
        self._csv_path = self.run_dir / "metrics.csv"
        if kind == "wandb":
            import wandb

            mode = os.environ.get("WANDB_MODE", mode)
            # silent: wandb's banner and run summary are ~30 lines a stage (and around every stage of stage=all);
            # the one line below says where the run went, which is what that banner was for
            self._wandb = wandb.init(project=project, entity=entity, name=name, mode=mode,
                                     dir=str(self.run_dir), config=config or {}, reinit="finish_previous",
                                     settings=wandb.Settings(silent=True))
            self.where = wandb_location(self._wandb, mode)
            if self.where:
                log.info("%s", self.where)

    def log(self, metrics: dict[str, Any], step: int | None = None) -> None:
        if self.kind == "wandb":
            self._wandb.log(metrics, step=step)
        elif self.kind == "csv":
            self.run_dir.mkdir(parents=True, exist_ok=True)
            new = not self._csv_path.exists()
            with open(self._csv_path, "a", newline="") as f:
                w = csv.writer(f)
                if new:
                    w.writerow(["step", "key", "value"])
                for k, v in metrics.items():
                    w.writerow([step, k, v])

    def log_image(self, key: str, path: str | Path) -> None:
        # checked for every kind, so that a stage naming a picture it never wrote fails in tests (logger=none)
        # and not only later under wandb
        if not Path(path).is_file():
            raise FileNotFoundError(f"log_image({key!r}): no picture at {path}")
        if self.kind == "wandb":
            import wandb

            self._wandb.log({key: wandb.Image(str(path))})

    def log_table(self, key: str, columns: list[str], rows: list[list]) -> None:
        if self.kind == "wandb":
            import wandb

            self._wandb.log({key: wandb.Table(columns=columns, data=rows)})

    def lightning(self, save_dir: Path):
        """The matching Lightning logger (or False)."""
        if self.kind == "wandb":
            from lightning.pytorch.loggers import WandbLogger

            return WandbLogger(experiment=self._wandb, save_dir=str(save_dir))
        if self.kind == "csv":
            from lightning.pytorch.loggers import CSVLogger

            return CSVLogger(save_dir=str(save_dir), name=self.name)
        return False

    def finish(self, exit_code: int = 0) -> None:
        if self._wandb is not None:
            self._wandb.finish(exit_code=exit_code)
            self._wandb = None
