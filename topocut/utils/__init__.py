"""Run-time helpers shared by the stages: seeding, device choice, loggers, progress bars."""

from topocut.utils.progress import progress_bar
from topocut.utils.runtime import DeviceUnavailable, resolve_device, seed_everything_all

__all__ = ["resolve_device", "seed_everything_all", "DeviceUnavailable", "progress_bar"]
