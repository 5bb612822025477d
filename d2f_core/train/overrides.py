"""``KEY=VALUE`` overrides of a model config, as ``d2f-train export --set`` and
``d2f-train depth export --set`` take them (one home for both stages).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

__all__ = ["apply_overrides"]


def apply_overrides(config: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """``config`` with ``KEY=VALUE`` items applied, each value cast to the key's type."""
    config = dict(config)
    for item in overrides:
        key, sep, value = item.partition("=")
        if not sep or key not in config:
            raise ValueError(
                f"--set needs KEY=VALUE with KEY one of {sorted(config)}, got {item!r}"
            )
        kind = type(config[key])
        if kind is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"--set {key}= needs true or false, got {value!r}")
            config[key] = value.lower() in ("true", "1")
        else:
            config[key] = kind(value)
    return config
