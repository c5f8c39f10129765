"""Run-time helpers shared by the stages: seeding, device choice, loggers, progress bars."""

from topocut.utils.runtime import resolve_device, seed_everything_all, DeviceUnavailable
from topocut.utils.progress import progress_bar

__all__ = ["resolve_device", "seed_everything_all", "DeviceUnavailable", "progress_bar"]
