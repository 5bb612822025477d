"""The teachers' weight files: one ``.pt`` each in ``assets/weights/``, float16 on disk
(float32 for a teacher whose outputs float16 would move past its port's bar).

A file holds ``{"format": FORMAT, "teacher": name, "config": {...}, "state_dict": {...}}``;
it is read with ``torch.load(weights_only=True)`` (tensors and plain containers only) and
its tensors come back as float32. :func:`save_teacher` writes one (``d2f-train
port-teachers``), :func:`load_teacher` builds the module a file names and loads it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..bundled import assets_dir
from ..networks import read_torch_file

__all__ = ["FORMAT", "load_teacher", "save_teacher", "teacher_path"]

#: the ``format`` field of a teacher's weight file
FORMAT = "d2f-teacher-1"


def teacher_path(name: str) -> Path:
    """The shipped weights of teacher ``name``: ``assets/weights/teacher_<name>.pt``."""
    return assets_dir() / "weights" / f"teacher_{name}.pt"


def save_teacher(
    path: str | Path,
    name: str,
    config: Mapping[str, Any],
    state_dict: Mapping[str, torch.Tensor],
    dtype: torch.dtype = torch.float16,
) -> Path:
    """Write ``state_dict`` (floating tensors as ``dtype``: float16 unless a teacher needs
    float32 to match its original) with its teacher's ``name`` and the ``config`` its module
    is built from."""
    half = {
        k: (v.detach().cpu().to(dtype) if v.is_floating_point() else v.detach().cpu()).contiguous()
        for k, v in state_dict.items()
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {"format": FORMAT, "teacher": name, "config": dict(config), "state_dict": half}, path
    )
    return path


def load_teacher(
    build: Callable[..., nn.Module], name: str, path: str | Path | None = None
) -> nn.Module:
    """The module ``build(**config)`` with the weights of ``path`` (default: the shipped
    file of teacher ``name``), in eval mode, float32.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a d2f teacher file, is another teacher's, or its tensors
            do not fit the module.
    """
    path = teacher_path(name) if path is None else Path(path)
    raw = read_torch_file(
        path,
        not_found=f"{name} teacher weights not found",
        unreadable=f"cannot read the {name} teacher weights {path}",
    )
    if not isinstance(raw, Mapping) or raw.get("format") != FORMAT:
        raise ValueError(f"{path} is not a d2f teacher weights file")
    if raw.get("teacher") != name:
        raise ValueError(f"{path} holds the {raw.get('teacher')!r} teacher, not {name!r}")
    config, state = raw.get("config"), raw.get("state_dict")
    if not isinstance(config, Mapping) or not isinstance(state, Mapping):
        raise ValueError(f"{path} is not a d2f teacher weights file")
    module = build(**config)
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    bad = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or bad:
        raise ValueError(
            f"{path} does not fit the {name} teacher: {len(missing)} missing, "
            f"{len(unexpected)} unexpected and {len(bad)} misshapen tensors"
        )
    module.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    return module.eval()
