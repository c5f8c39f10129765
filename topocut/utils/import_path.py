"""``module.path:ClassName`` entries: your own policy (eval.policies) or task (eval.tasks) named by where it lives."""


def is_import_path(entry) -> bool:
    """Whether a config entry names a class by import path (``module.path:ClassName``) rather than a registered name."""
    return isinstance(entry, str) and ":" in entry
