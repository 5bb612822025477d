"""The app's "Depth source" control: the sources a photo offers and the map ``prepare`` gets.

The sources are those of :mod:`d2f_core.depth.sources`: the phone depth stored in the photo,
the user's own map, the shipped network (offline) and, when ``transformers`` is installed
(the ``hub`` extra), any Hugging Face depth-estimation model named by its id or a folder on
the server. "Automatic" keeps the order the app always used: the user's map, else the
photo's own depth, else the network. The scene cache keys on the source, so switching back
to a source already computed for the photo is instant.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from d2f_core.depth import sources as depth_sources

AUTO = "auto"
#: ``(label, value)`` of every choice, in the order shown.
CHOICES = (
    ("Automatic (your map, else the photo's own, else the network)", AUTO),
    ("The photo's own depth (phone)", "embedded"),
    ("Your depth map (below)", "file"),
    ("Shipped network (offline)", "d2f"),
    ("Hugging Face model (id or folder below)", "transformers"),
)
HUB_PLACEHOLDER = "depth-anything/Depth-Anything-V2-Small-hf"


def has_embedded_depth(payload: Any, files: Any = None) -> bool | None:
    """Whether an uploaded photo carries phone depth (``None`` when that cannot be told, or
    when ``files``, an :class:`app.uploads.UploadGate`, does not allow opening the path)."""
    from d2f_core.io import read_embedded_depth

    path = payload.get("path") if isinstance(payload, dict) else payload
    if not path or (files is not None and not files.allows(path)):
        return None
    try:
        return read_embedded_depth(str(path)) is not None
    except (OSError, ValueError):
        return None


def choices(has_embedded: bool | None = None) -> list[tuple[str, str]]:
    """The choices to offer: the photo's own depth only when it has some (``None``: not
    known yet, offered), the hub model only when ``transformers`` is installed."""
    hub = depth_sources.hub_available()
    return [
        (label, value)
        for label, value in CHOICES
        if (value != "embedded" or has_embedded is not False) and (value != "transformers" or hub)
    ]


def resolve(choice: Any, hub_model: Any, has_map: bool, has_embedded: bool) -> tuple[str, str]:
    """The source for this photo, ``"file"``, ``"embedded"``, ``"d2f"`` or
    ``"transformers:MODEL"``, and a note for the user (``""`` when none): a choice this
    photo cannot have (no phone depth, no map uploaded) falls back to the automatic one.

    Raises:
        ValueError: a hub model chosen without a name, or without ``transformers`` installed,
            with a message for the user.
    """
    choice = AUTO if choice in (None, "") else str(choice)
    automatic = "file" if has_map else "embedded" if has_embedded else "d2f"
    if choice == AUTO:
        return automatic, ""
    if choice == "embedded" and not has_embedded:
        return automatic, "This photo carries no phone depth; " + _using(automatic)
    if choice == "file" and not has_map:
        return automatic, "No depth map was uploaded; " + _using(automatic)
    if choice == "transformers":
        if not depth_sources.hub_available():
            raise ValueError(
                "Hugging Face models need the transformers package on the server: "
                f"{depth_sources.HUB_EXTRA_HINT}."
            )
        name = str(hub_model or "").strip()
        if not name:
            raise ValueError(
                f"Name a Hugging Face depth model (for example {HUB_PLACEHOLDER}) or a folder "
                "on the server in the box below the depth source."
            )
        return f"transformers:{name}", ""
    if choice not in ("embedded", "file", "d2f"):
        raise ValueError(f"Unknown depth source {choice!r}.")
    return choice, ""


def _using(source: str) -> str:
    words = {"file": "your map", "embedded": "the photo's own depth", "d2f": "the network"}
    return f"using {words[source]}."


def pick(source: str, decoded: np.ndarray | None, photo: Any) -> tuple[np.ndarray | None, bool]:
    """The ready map for ``source`` (the decoded user map, the photo's own depth, or ``None``
    when ``prepare`` computes it) and whether it is the user's map."""
    if source == "file":
        return decoded, True
    if source == "embedded":
        return photo.disparity, False
    return None, False


def scene_key(content_key: str, source: str) -> str:
    """The scene cache's key: the pixels (and map) with the source that made the map."""
    return f"{content_key}|{source}"


def prepare(model: Any, image: np.ndarray, disparity: np.ndarray | None, source: str) -> Any:
    """``model.prepare`` for ``source``: a ready map is passed with its source's name, the
    network and hub models run inside ``prepare``."""
    if disparity is None:
        return model.prepare(image, depth=source)
    output = "disparity map" if source == "file" else "phone depth"
    return model.prepare(image, depth=depth_sources.DepthMap(disparity, source, output))


def describe(scene: Any, fallback: str) -> str:
    """For the status line: the hub model and what it gave, the shipped network, or
    ``fallback`` (the app's words for the user's map or the phone's depth)."""
    name = getattr(scene, "disparity_source", "")
    if name.startswith("transformers:"):
        return f"{name} ({getattr(scene, 'disparity_output', '')})"
    if name == "d2f":
        return "shipped network (d2f)"
    return fallback
