"""The app's "Depth source" control: the sources a photo offers and the map ``prepare`` gets.

The sources are those of :mod:`d2f_core.depth.sources`: the phone depth stored in the photo,
the user's own map, the shipped network (offline) and, when ``transformers`` is installed
(the ``hub`` extra), the Hugging Face depth-estimation models that the server's operator
allows (:class:`HubPolicy`, ``d2f-app --depth-models``). "Automatic" keeps the order the app
always used: the user's map, else the photo's own depth, else the weights' own default (the
scene teachers with the network's subjects for the shipped weights). The scene cache
keys on the source, so switching back to a source already computed for the photo is instant.

A client never makes the server download a model or look at its folders: it picks one of the
operator's models, which must be in the local Hugging Face cache (checked in milliseconds,
before the photo is decoded); any other name is refused. Free-text ids and folders are for
local use only (``--allow-any-depth-model``, bound to 127.0.0.1), and still never downloaded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from d2f_core.depth import sources as depth_sources

AUTO = "auto"
#: ``(label, value)`` of every choice, in the order shown.
CHOICES = (
    ("Automatic (your map, else the photo's own, else the scene teachers)", AUTO),
    ("The photo's own depth (phone)", "embedded"),
    ("Your depth map (below)", "file"),
    ("Scene teachers with the network's subjects (offline)", "scene"),
    ("Shipped network alone (offline, fastest)", "d2f"),
    ("Hugging Face model (id or folder below)", "transformers"),
)
#: What the app tells of the shipped network under the depth source choice.
NETWORK_NOTE = (
    "Without phone depth the depth is guessed: by default from small scene networks (sky, "
    "ground, walls and objects) with the shipped network's subjects stood in front. Right "
    "for one clear subject (a person, a pet, an object), for tall subjects and for posts "
    "crossing the frame; rooms, tunnels and shelves come out in their order, but furniture "
    "and a fruit bowl's many similar objects can still be misplaced. If the blur lands on "
    "your subject, click the subject."
)
HUB_PLACEHOLDER = "depth-anything/Depth-Anything-V2-Small-hf"
#: Longest model id or folder name taken from a client (hub ids are at most 96 + 1 + 96).
MAX_MODEL_NAME = 200


@dataclass(frozen=True)
class HubPolicy:
    """Which Hugging Face depth models the clients of this server may use.

    Attributes:
        models: the operator's list (``d2f-app --depth-models ID,...``): hub ids or folders,
            offered to clients in a list.
        any_model: clients may also name any hub id or folder on the server
            (``--allow-any-depth-model``: local use only, the server bound to 127.0.0.1).
    """

    models: tuple[str, ...] = ()
    any_model: bool = False

    @property
    def offered(self) -> bool:
        """Whether clients may use a hub model at all."""
        return bool(self.models) or self.any_model


#: The policy in force: no hub model until the operator allows some (:func:`configure`).
POLICY = HubPolicy()


def parse_models(text: str | None) -> tuple[str, ...]:
    """``"a/b, c/d"`` -> ``("a/b", "c/d")`` (duplicates and empty items dropped).

    Raises:
        ValueError: a name longer than :data:`MAX_MODEL_NAME`.
    """
    names: list[str] = []
    for item in (text or "").split(","):
        name = item.strip()
        if len(name) > MAX_MODEL_NAME:
            raise ValueError(f"a model name is at most {MAX_MODEL_NAME} characters: {name[:60]}...")
        if name and name not in names:
            names.append(name)
    return tuple(names)


def configure(models: tuple[str, ...] | list[str] = (), any_model: bool = False) -> HubPolicy:
    """Set the policy in force (``d2f-app`` does, from its options) and return it."""
    global POLICY
    POLICY = HubPolicy(tuple(models), bool(any_model))
    return POLICY


def check_hub_model(name: Any, policy: HubPolicy | None = None) -> str:
    """The hub model a client named, checked: allowed by ``policy`` (default :data:`POLICY`)
    and loadable from local files only (:func:`d2f_core.depth.sources.hub_model_cached`).
    Takes milliseconds, touches no network and downloads nothing.

    Raises:
        ValueError: with a message for the user.
    """
    policy = POLICY if policy is None else policy
    text = str(name or "").strip()
    if not policy.offered:
        raise ValueError(
            "This server offers no Hugging Face depth model (its operator can offer some with "
            "d2f-app --depth-models)."
        )
    if len(text) > MAX_MODEL_NAME:
        raise ValueError(
            f"The model name is {len(text)} characters long; at most {MAX_MODEL_NAME} are accepted."
        )
    listed = ", ".join(policy.models)
    if not text:
        if policy.any_model:
            raise ValueError(
                f"Name a Hugging Face depth model (for example {HUB_PLACEHOLDER}) or a folder "
                "on the server in the box below the depth source."
            )
        raise ValueError(f"Choose a Hugging Face depth model from the list: {listed}.")
    if text not in policy.models and not policy.any_model:
        raise ValueError(f"That model is not offered here; this server offers: {listed}.")
    if not depth_sources.hub_model_cached(text):
        raise ValueError(
            f"The model {text} is not available on this server: it is not in the local "
            "Hugging Face cache (nor a folder holding a model), and the app never downloads "
            f"one; the server's operator can fetch it with: hf download {text}"
        )
    return text


def check_choice(choice: Any, hub_model: Any) -> None:
    """Refuse at once a hub model this server does not offer or has not cached (before the
    photo is decoded: the render slot the event holds is released in milliseconds)."""
    if choice == "transformers":
        _hub_extra()
        check_hub_model(hub_model)


def _hub_extra() -> None:
    if not depth_sources.hub_available():
        raise ValueError(
            "Hugging Face models need the transformers package on the server: "
            f"{depth_sources.HUB_EXTRA_HINT}."
        )


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


def offer(payload: Any, files: Any = None) -> dict:
    """The update of the depth source control for a photo just put in the panel (an upload
    or a bundled sample): the photo's own depth is offered only when it has some."""
    import gradio as gr

    return gr.update(choices=choices(has_embedded_depth(payload, files)))


def choices(has_embedded: bool | None = None) -> list[tuple[str, str]]:
    """The choices to offer: the photo's own depth only when it has some (``None``: not
    known yet, offered), the hub model only when ``transformers`` is installed and the
    operator offers hub models (:data:`POLICY`)."""
    hub = POLICY.offered and depth_sources.hub_available()
    return [
        (label, value)
        for label, value in CHOICES
        if (value != "embedded" or has_embedded is not False) and (value != "transformers" or hub)
    ]


def resolve(
    choice: Any, hub_model: Any, has_map: bool, has_embedded: bool, default: str = "d2f"
) -> tuple[str, str]:
    """The source for this photo, ``"file"``, ``"embedded"``, ``"scene"``, ``"d2f"`` or
    ``"transformers:MODEL"``, and a note for the user (``""`` when none): a choice this
    photo cannot have (no phone depth, no map uploaded) falls back to the automatic one,
    which ends in ``default`` (the model's ``config.depth_source``).

    Raises:
        ValueError: a hub model chosen without a name, one this server does not offer or has
            not cached (:func:`check_hub_model`), or without ``transformers`` installed, with
            a message for the user.
    """
    choice = AUTO if choice in (None, "") else str(choice)
    automatic = "file" if has_map else "embedded" if has_embedded else default
    if choice == AUTO:
        return automatic, ""
    if choice == "embedded" and not has_embedded:
        return automatic, "This photo carries no phone depth; " + _using(automatic)
    if choice == "file" and not has_map:
        return automatic, "No depth map was uploaded; " + _using(automatic)
    if choice == "transformers":
        _hub_extra()
        return f"transformers:{check_hub_model(hub_model)}", ""
    if choice not in ("embedded", "file", "d2f", "scene"):
        raise ValueError(f"Unknown depth source {choice!r}.")
    return choice, ""


def _using(source: str) -> str:
    words = {
        "file": "your map",
        "embedded": "the photo's own depth",
        "d2f": "the network",
        "scene": "the scene teachers",
    }
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
    if name == "scene":  # "scene teachers' map (parse, objects, network)": what ran
        return str(getattr(scene, "disparity_output", "scene teachers' map"))
    return fallback
