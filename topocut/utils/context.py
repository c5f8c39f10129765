"""What every stage receives besides its own explicit arguments."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from topocut.data.store import ArtifactStore
from topocut.utils.logger import RunLogger


@dataclass
class RunContext:
    store: ArtifactStore
    run_dir: Path  # this run's Hydra output directory (status.json, renders, logs)
    device: str  # "cpu" | "cuda"
    seed: int
    logger: RunLogger
    progress: bool = True
    config: dict[str, Any] = field(default_factory=dict)  # resolved config, for manifests only
    overrides: list[str] = field(default_factory=list)
