"""A check the config dataclasses' ``validate()`` methods share, so that a bad choice reads the same in every group."""


def check_choice(key: str, value, valid) -> None:
    """ValueError unless ``value`` is one of ``valid``: "policy.graph='x' is not valid; choose one of uniform, ..."."""
    if value not in valid:
        raise ValueError(f"{key}={value!r} is not valid; choose one of {', '.join(valid)}")
