"""Run-time helpers shared by the stages: seeding, device choice, loggers, progress bars.

Exports are lazy (``topocut.utils.lazy``): the packages whose own exports are lazy import that helper from here
without pulling in numpy or rich."""
from topocut.utils.lazy import lazy_exports

_EXPORTS = {"resolve_device": "topocut.utils.runtime", "seed_everything_all": "topocut.utils.runtime",
            "DeviceUnavailable": "topocut.utils.runtime", "progress_bar": "topocut.utils.progress"}
__all__ = ["resolve_device", "seed_everything_all", "DeviceUnavailable", "progress_bar"]
__getattr__ = lazy_exports(__name__, _EXPORTS)
