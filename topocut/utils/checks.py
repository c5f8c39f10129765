"""Checks the config dataclasses' ``validate()`` methods share, so that a bad value reads the same in every group."""


def check_choice(key: str, value, valid) -> None:
    """ValueError unless ``value`` is one of ``valid``: "policy.graph='x' is not valid; choose one of uniform, ..."."""
    if value not in valid:
        raise ValueError(f"{key}={value!r} is not valid; choose one of {', '.join(valid)}")


def check_positive(prefix: str, obj, keys) -> None:
    """ValueError unless every ``obj.<key>`` of ``keys`` is > 0: "task.pen.speed=0 must be > 0" (prefix "task.pen")."""
    for k in keys:
        if getattr(obj, k) <= 0:
            raise ValueError(f"{prefix}.{k}={getattr(obj, k)} must be > 0")
