"""Reading torch files safely: checkpoints and state dicts from LOCAL paths, tensors and plain
containers only (``weights_only``), with one-line reasons when a file is refused.
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

__all__ = ["load_local_state_dict", "optimizer_state_on_cpu", "read_torch_file"]


def read_torch_file(path: str | Path, *, not_found: str, unreadable: str) -> Any:
    """``torch.load`` of a LOCAL file, tensors and plain containers only (``weights_only``).

    Raises:
        FileNotFoundError: ``"{not_found}: {path}"`` when ``path`` is not a file.
        ValueError: ``"{unreadable}: {error}"`` when the file cannot be read (corrupt,
            truncated, not a torch file, or holding more than tensors and containers).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{not_found}: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle/zip errors come in many types
        raise ValueError(f"{unreadable}: {_load_failure(exc)}") from exc


def _load_failure(exc: BaseException) -> str:
    """One line on why ``torch.load(weights_only=True)`` refused a file. Torch's own text
    runs over several lines and advises ``weights_only=False``, which would run whatever
    code the file holds: it is never passed on."""
    text = str(exc)
    if text.startswith("Weights only load failed"):
        blocked = re.search(r"GLOBAL (\S+)", text, re.IGNORECASE)
        if blocked:
            return f"it holds a Python object ({blocked.group(1)}), not only tensors"
        return "not a PyTorch checkpoint, or cut short"
    if "PytorchStreamReader" in text:
        return "its archive is damaged or cut short"
    if isinstance(exc, (pickle.UnpicklingError, KeyError, EOFError)):
        return "not a PyTorch checkpoint, or cut short"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def optimizer_state_on_cpu(state: dict[str, Any]) -> dict[str, Any]:
    """An optimiser's ``state_dict()`` with its per-parameter tensors on the CPU, for a
    checkpoint that loads on any machine (``load_state_dict`` moves them back to the
    parameters' device)."""
    return {
        **state,
        "state": {
            i: {k: v.detach().cpu() if isinstance(v, Tensor) else v for k, v in s.items()}
            for i, s in state["state"].items()
        },
    }


def load_local_state_dict(path: str | Path, what: str) -> Mapping[str, Tensor]:
    """Read a state dict of tensors from a LOCAL file (optionally wrapped in
    ``{"state_dict": ...}`` or ``{"model": ...}``); ``what`` names the weights in messages.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is unreadable or does not hold a state dict of tensors.
    """
    raw = read_torch_file(
        path,
        not_found=f"{what} weights file not found",
        unreadable=f"cannot read {what} weights from {path}",
    )
    if isinstance(raw, Mapping):
        for key in ("state_dict", "model"):
            if key in raw and isinstance(raw[key], Mapping):
                raw = raw[key]
                break
    if not isinstance(raw, Mapping) or not all(
        isinstance(k, str) and isinstance(v, Tensor) for k, v in raw.items()
    ):
        raise ValueError(f"{path} does not hold a state dict of tensors")
    return raw
