"""Where a photo's depth comes from: one registry that turns a depth source into disparity.

Every caller (``D2F.prepare``, the ``d2f`` CLI, the app) asks :func:`depth_map` for the map;
the result is a :class:`DepthMap`, ``H x W`` float32 disparity in [0, 1] (1 = nearest) at the
photo's size (the ``scene`` source's at its working size, with the photo's aspect), with the
source's name and what kind of output it gave.

Sources (:data:`SOURCES`), written as a string:

``embedded``
    The phone depth stored in the photo (Google Lens Blur JPEG, Apple portrait JPEG or HEIC),
    read by :func:`d2f_core.io.load_photo`; the photo must be passed as its ``Photo``.
``file:PATH``
    A user's depth or disparity map (PNG 8/16-bit, ``.npy``, PFM, float TIFF), read by
    :func:`d2f_core.io.load_depth`.
``d2f``
    The shipped D2F defocus network alone (the fast source; runs offline, weights in
    ``assets/weights/``).
``scene``
    The scene teachers run at inference (:mod:`d2f_core.depth.scene_source`: the scene parse,
    the silhouette, the VOC objects and the indoor depth, as torch modules with shipped
    weights) with the D2F network's subjects stood on their map and its own map blended in;
    offline; the shipped weights' default for a photo with no depth of its own
    (``config.depth_source``).
``transformers:MODEL``
    Any depth-estimation model that Hugging Face ``transformers`` loads with
    ``AutoImageProcessor`` and ``AutoModelForDepthEstimation``: a hub id such as
    ``depth-anything/Depth-Anything-V2-Small-hf`` or a folder written by
    ``save_pretrained``. Needs the ``hub`` extra (``pip install "d2f[hub]"``). Two kinds of
    output are handled (:func:`model_output_kind`):

    * relative inverse depth (Depth Anything V1/V2 relative models, DPT with a ViT backbone):
      larger is nearer, known up to scale and shift; normalised to [0, 1]
      (:func:`relative_to_disparity`);
    * metric depth in metres (ZoeDepth, Depth Pro, GLPN, Depth Anything metric models,
      DPT with a DINOv2 backbone): larger is farther; inverted, then normalised
      (:func:`metric_to_disparity`).

Network access: nothing here touches the network at import time, and ``transformers`` is
imported only when a hub source is used. A model is first looked up in the local Hugging
Face cache; only when it is not there, and ``HF_HUB_OFFLINE`` (or ``TRANSFORMERS_OFFLINE``)
is not set, is it downloaded, with a log message saying so. A local folder never touches the
network.
"""

from __future__ import annotations

import importlib.util
import inspect
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputTypeError
from ..io.depth import check_aspect

__all__ = [
    "DEFAULT_SOURCE",
    "HUB_EXTRA_HINT",
    "SOURCES",
    "DepthMap",
    "DepthSource",
    "depth_map",
    "hub_available",
    "hub_model_cached",
    "metric_to_disparity",
    "model_output_kind",
    "parse_source",
    "relative_to_disparity",
]

logger = logging.getLogger(__name__)

#: The source used when none is named.
DEFAULT_SOURCE = "d2f"

#: Every source, with a line saying what it is.
SOURCES: dict[str, str] = {
    "embedded": "the phone depth stored in the photo (Google Lens Blur, Apple portrait)",
    "file": "a depth or disparity map file (file:PATH)",
    "d2f": "the shipped D2F defocus network alone (offline; the fastest)",
    "scene": "the scene teachers' map with the network's subjects (offline; the shipped "
    "weights' default)",
    "transformers": "a Hugging Face depth-estimation model (transformers:MODEL_ID or a folder)",
}

HUB_EXTRA_HINT = 'pip install "d2f[hub]" (or pip install -e ".[hub]" in a checkout)'

#: Long side (px) a photo is shrunk to before a hub model's processor sees it: the processors
#: resize to 384-1536 px anyway, and shrinking a 12 MP photo in numpy first saves seconds.
HUB_MAX_SIDE = 1536

RELATIVE = "relative inverse depth"
METRIC = "metric depth"

# model types whose depth head predicts metres
_METRIC_MODEL_TYPES = frozenset({"zoedepth", "depth_pro", "glpn", "prompt_depth_anything"})


@dataclass(frozen=True)
class DepthSource:
    """A parsed source: ``kind`` is a key of :data:`SOURCES`, ``arg`` its path or model id."""

    kind: str
    arg: str = ""

    @property
    def name(self) -> str:
        """The source as it is written: ``"d2f"``, ``"transformers:depth-anything/..."``."""
        return f"{self.kind}:{self.arg}" if self.arg else self.kind


@dataclass
class DepthMap:
    """A disparity map and where it came from.

    Attributes:
        disparity: ``H x W`` float32 in [0, 1], 1 = nearest, at the photo's size; a
            ``predicted`` map at the size it was made, with the photo's aspect.
        source: the source's name (:attr:`DepthSource.name`).
        output: what the source gave before it was turned into disparity: ``"relative
            inverse depth"``, ``"metric depth"``, ``"apple_mpo phone depth"``,
            ``"disparity map"``, ``"depth map"`` or ``"D2F network disparity"``.
        focus: a focal disparity that came with the map (a phone's focus), or ``None``.
        predicted: a coarse map the model predicts (the ``scene`` source's), which
            :meth:`D2F.prepare` brings straight to the network's pass size and renders
            there like the network's own, not at the photo's size as a measured map.
    """

    disparity: np.ndarray
    source: str
    output: str
    focus: float | None = None
    predicted: bool = False

    def describe(self) -> str:
        """One line for logs and status lines: ``"transformers:X (relative inverse depth)"``."""
        return f"{self.source} ({self.output})"


def hub_available() -> bool:
    """Whether ``transformers`` is installed (without importing it)."""
    try:
        return importlib.util.find_spec("transformers") is not None
    except (ImportError, ValueError):  # a module entry of None (import blocked) or no spec
        return False


def parse_source(source: str | DepthSource) -> DepthSource:
    """Read a source string: ``"d2f"``, ``"embedded"``, ``"file:PATH"``,
    ``"transformers:MODEL"``.

    Raises:
        ValueError: an unknown source, or ``file``/``transformers`` without their argument.
    """
    if isinstance(source, DepthSource):
        return source
    if not isinstance(source, str):
        raise InputTypeError(f"depth source must be a string, got {type(source).__name__}")
    text = source.strip()
    kind, sep, arg = text.partition(":")
    kind = kind.strip().lower()
    arg = arg.strip()
    known = ", ".join(["embedded", "file:PATH", "d2f", "scene", "transformers:MODEL"])
    if kind not in SOURCES:
        raise ValueError(f"unknown depth source {source!r}; expected one of {known}")
    if kind in ("embedded", "d2f", "scene"):
        if arg:
            raise ValueError(f"depth source {kind!r} takes no argument, got {source!r}")
        return DepthSource(kind)
    if not arg:
        what, form = (
            ("a map file", "PATH") if kind == "file" else ("a model id or a folder", "MODEL")
        )
        raise ValueError(f"depth source {kind!r} needs {what}: write {kind}:{form}")
    return DepthSource(kind, arg)


# --------------------------------------------------------------------------- conversions


def relative_to_disparity(prediction: Any, *, robust: bool = True) -> np.ndarray:
    """Relative inverse depth (larger = nearer, any scale and shift) -> disparity in [0, 1].

    Normalised between its 0.5 and 99.5 percentiles (``robust``, maps of 1000 pixels or
    more) or its extremes; non-finite values are filled from their neighbours.

    Shape: ``H x W`` -> ``H x W`` float32, 1 = nearest.
    """
    from ..io.depth import depth_to_disparity

    return depth_to_disparity(_as_map(prediction), kind="disparity", robust=robust, name="model")


def metric_to_disparity(depth: Any, *, robust: bool = True) -> np.ndarray:
    """Metric depth (distance, larger = farther) -> disparity in [0, 1] via ``1 / depth``.

    Zero, negative and non-finite depths are holes, filled from their neighbours; the
    inverse is normalised as in :func:`relative_to_disparity`.

    Shape: ``H x W`` -> ``H x W`` float32, 1 = nearest.
    """
    from ..io.depth import depth_to_disparity

    return depth_to_disparity(_as_map(depth), kind="depth", robust=robust, name="model")


def _as_map(values: Any) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().float().cpu().numpy()
    a = np.asarray(values, dtype=np.float64)
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"depth prediction must be an H x W map, got shape {a.shape}")
    return a


def model_output_kind(config: Any) -> str:
    """What a ``transformers`` depth model predicts: :data:`RELATIVE` or :data:`METRIC`.

    From its config: Depth Anything models say it (``depth_estimation_type``); ZoeDepth,
    Depth Pro, GLPN and Prompt Depth Anything predict metres; DPT predicts relative inverse
    depth with its ViT backbones (DPT-Large, DPT-Hybrid) and metres with a DINOv2 backbone
    (the NYU and KITTI heads); anything else is taken as relative inverse depth.
    """
    model_type = str(getattr(config, "model_type", ""))
    if getattr(config, "depth_estimation_type", None) == "metric":
        return METRIC
    if model_type in _METRIC_MODEL_TYPES:
        return METRIC
    backbone = getattr(config, "backbone_config", None)
    if model_type == "dpt" and getattr(backbone, "model_type", None) == "dinov2":
        return METRIC
    return RELATIVE


# --------------------------------------------------------------------------- the registry


def depth_map(
    source: str | DepthSource,
    image: Any,
    *,
    photo: Any = None,
    model: Any = None,
    file_kind: str = "disparity",
    near: str | None = None,
    zero_is_hole: bool | None = None,
    device: str | torch.device | None = None,
) -> DepthMap:
    """The disparity map of ``image`` from ``source``.

    Args:
        source: a source string (see the module docstring) or a :class:`DepthSource`.
        image: the photo, ``H x W x 3`` numpy (uint8, or float in [0, 1]) or a
            ``[1, 3, H, W]`` tensor in [0, 1].
        photo: the :class:`d2f_core.io.Photo` the image came from (``embedded`` reads its
            depth).
        model: a ``D2F`` (``d2f`` runs its defocus network).
        file_kind, near, zero_is_hole: how a ``file`` map is read
            (:func:`d2f_core.io.depth_to_disparity`).
        device: where a hub model runs (default: CPU, or ``model``'s device).

    Returns:
        :class:`DepthMap` at the photo's size (the ``scene`` source's at its working size).

    Raises:
        ValueError: an unknown source, a photo without embedded depth, an unreadable map, a
            hub model that cannot be loaded (not installed, not cached while offline, not a
            depth model), or no ``model`` for ``d2f``.
    """
    spec = parse_source(source)
    if spec.kind == "scene":  # reads a small copy: the photo is not copied whole
        return _scene_map(spec, image, model)
    image_np = _image_array(image)
    size = image_np.shape[:2]
    if spec.kind == "embedded":
        disparity = getattr(photo, "disparity", None)
        if disparity is None:
            raise ValueError(
                "depth source 'embedded': the photo carries no phone depth (Google Lens Blur "
                "or Apple portrait); choose d2f, file:PATH or transformers:MODEL"
            )
        info = getattr(photo, "depth_info", None) or {}
        disparity = np.asarray(disparity, dtype=np.float32)
        check_aspect(disparity.shape, size, "embedded depth")
        d = _fit(disparity, size)
        kind = info.get("source", "phone")
        return DepthMap(d, spec.name, f"{kind} phone depth", getattr(photo, "focus", None))
    if spec.kind == "file":
        from ..io.depth import load_depth

        path = Path(spec.arg).expanduser()
        if not path.exists():  # a FIFO or a device: load_depth says what it is
            raise ValueError(f"depth source 'file': no such file {spec.arg!r}")
        d = load_depth(
            path, kind=file_kind, near=near, size=size, guide=image_np, zero_is_hole=zero_is_hole
        )
        return DepthMap(d, spec.name, f"{file_kind} map")
    if spec.kind == "d2f":
        if model is None or not hasattr(model, "predict_disparity"):
            raise ValueError("depth source 'd2f' needs the D2F model (its weights) to run")
        return DepthMap(_d2f_map(model, image_np), spec.name, "D2F network disparity")
    if device is None and model is not None and hasattr(model, "device"):
        device = model.device
    d, kind = _hub_map(spec.arg, image_np, torch.device(device or "cpu"))
    return DepthMap(d, spec.name, kind)


def _scene_map(spec: DepthSource, image: Any, model: Any) -> DepthMap:
    """:func:`depth_map` of the ``scene`` source: the teachers and the network read a copy
    of at most :data:`~.scene_source.READ_SIDE` px made from the checked photo (at 12 MP,
    converting the whole photo to an array first cost about 0.4 s); the map is at
    :func:`~.scene_source.work_size`."""
    if model is None or not hasattr(model, "scene_maps"):
        raise ValueError("depth source 'scene' needs the D2F model (its subjects) to run")
    from ..rendering import image_tensor
    from .scene_source import reading_copy, scene_maps, shared_teachers, work_size

    x = image_tensor(image)
    size = (int(x.shape[-2]), int(x.shape[-1]))
    with torch.no_grad():
        found = scene_maps(reading_copy(x), shared_teachers(), model, size=work_size(*size))
    ran = ", ".join(found.ran)
    # at its own size: brought to the photo's, a 12 MP map cost 0.15 s to make, check and
    # bring down to the pass again
    disparity = np.clip(found.disparity, 0.0, 1.0).astype(np.float32, copy=False)
    return DepthMap(disparity, spec.name, f"scene teachers' map ({ran})", predicted=True)


def _image_array(image: Any) -> np.ndarray:
    """``H x W x 3`` float32 in [0, 1] from anything ``rendering.image_tensor`` accepts."""
    from ..rendering import image_tensor

    return image_tensor(image)[0].permute(1, 2, 0).contiguous().cpu().numpy()


def _fit(disparity: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a map to ``size`` bilinearly (antialiased when shrinking), clipped to [0, 1]."""
    if disparity.shape == tuple(size):
        return np.clip(disparity, 0.0, 1.0).astype(np.float32, copy=False)
    from ..sizing import resize

    t = torch.from_numpy(np.ascontiguousarray(disparity, dtype=np.float32))[None, None]
    return resize(t, tuple(size))[0, 0].clamp_(0, 1).numpy()


def _d2f_map(model: Any, image: np.ndarray) -> np.ndarray:
    """The D2F network's map at the pass ``D2F.prepare`` would use, at the photo's size."""
    from ..sizing import resize  # the pipeline's own resize, for the same map

    size = image.shape[:2]
    with torch.no_grad():
        x = torch.from_numpy(image).permute(2, 0, 1)[None].to(model.device)
        lr = model.pass_size(size)
        d = model.predict_disparity(resize(x, lr).clamp_(0, 1), photo=x)  # [1,1,h,w]
        return resize(d, size)[0, 0].clamp_(0, 1).cpu().numpy()


# --------------------------------------------------------------------------- hub models


def _offline() -> bool:
    """``HF_HUB_OFFLINE`` / ``TRANSFORMERS_OFFLINE``, read now (the libraries read them once,
    at import)."""
    flags = (os.environ.get("HF_HUB_OFFLINE"), os.environ.get("TRANSFORMERS_OFFLINE"))
    return any(str(v).strip().upper() in ("1", "ON", "YES", "TRUE") for v in flags if v)


#: Files a cached hub model needs besides ``config.json``: its processor's settings and one
#: of its weight files.
_PROCESSOR_FILE = "preprocessor_config.json"
_WEIGHT_FILES = (
    "model.safetensors",
    "model.safetensors.index.json",
    "pytorch_model.bin",
    "pytorch_model.bin.index.json",
)


def hub_model_cached(model_id: str) -> bool:
    """Whether a hub depth model can be loaded without the network: a folder holding a
    ``config.json``, or a hub id whose config, processor settings and weights are in the
    local Hugging Face cache. Looks at local files only (milliseconds); never downloads.
    A name that is neither (too long, malformed) is not cached."""
    try:
        folder = Path(model_id).expanduser()
        if folder.is_dir():
            return (folder / "config.json").is_file()
        if model_id.startswith(("/", ".", "~")) or folder.exists():
            return False
    except (OSError, ValueError, RuntimeError):  # a name too long for a path, a NUL byte
        return False
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:
        return False

    def cached(filename: str) -> bool:
        try:
            return isinstance(try_to_load_from_cache(model_id, filename), str)
        except (ValueError, OSError):  # not a valid repo id
            return False

    return (
        cached("config.json")
        and cached(_PROCESSOR_FILE)
        and any(cached(name) for name in _WEIGHT_FILES)
    )


def _import_transformers() -> Any:
    try:
        import transformers
    except ImportError as exc:
        raise ValueError(
            "depth source 'transformers:...' needs the transformers package, which is not "
            f"installed ({exc}); install the hub extra: {HUB_EXTRA_HINT}"
        ) from None
    return transformers


_LOCK = threading.Lock()
_LOADED: dict[tuple[str, str], tuple[Any, Any]] = {}
#: Hub models kept loaded (a few hundred MB each for the larger ones).
_KEEP_LOADED = 2


def _processor_options(transformers: Any) -> dict[str, Any]:
    # the PIL/numpy image processors, which need no torchvision (d2f does not depend on it);
    # transformers 5 names them by backend, 4.x by use_fast
    major = int(str(transformers.__version__).split(".")[0])
    return {"backend": "pil"} if major >= 5 else {"use_fast": False}


def _load_hub_model(model_id: str, device: torch.device) -> tuple[Any, Any]:
    """``(processor, model)`` for a hub id or a local folder, in eval mode on ``device``;
    the last few are kept loaded."""
    key = (model_id, str(device))
    with _LOCK:
        if key in _LOADED:
            _LOADED[key] = _LOADED.pop(key)  # most recently used last
            return _LOADED[key]
    transformers = _import_transformers()
    folder = Path(model_id).expanduser()
    try:
        is_folder = folder.is_dir()
        exists = folder.exists()
    except OSError as exc:  # a name too long for a path
        shown = model_id if len(model_id) <= 80 else f"{model_id[:60]}... ({len(model_id)} chars)"
        raise ValueError(
            f"depth source 'transformers:{shown}': neither a model id nor a folder "
            f"({exc.strerror or exc})"
        ) from None
    if not is_folder and (model_id.startswith(("/", ".", "~")) or exists):
        # a path, not a hub id ("org/name"): never sent to the hub
        raise ValueError(f"depth source 'transformers:{model_id}': no such folder")
    name = str(folder) if is_folder else model_id
    options = _processor_options(transformers)

    def load(local_only: bool) -> tuple[Any, Any]:
        processor = transformers.AutoImageProcessor.from_pretrained(
            name, local_files_only=local_only, **options
        )
        net = transformers.AutoModelForDepthEstimation.from_pretrained(
            name, local_files_only=local_only
        )
        return processor, net

    try:
        try:
            processor, net = load(local_only=True)
        except OSError:
            if is_folder:
                raise
            if _offline():
                raise ValueError(
                    f"depth source 'transformers:{model_id}': the model is not in the local "
                    "Hugging Face cache and HF_HUB_OFFLINE is set; download it once on a "
                    "connected machine (unset HF_HUB_OFFLINE), or pass a local folder"
                ) from None
            logger.warning(
                "%s is not in the local Hugging Face cache; downloading it from the Hub", model_id
            )
            try:
                processor, net = load(local_only=False)
            except OSError as exc:
                raise ValueError(
                    f"depth source 'transformers:{model_id}': the model is not in the local "
                    f"Hugging Face cache and could not be downloaded ({_first_line(exc)}); "
                    "check the model id and the connection, or pass a local folder"
                ) from None
    except (OSError, ValueError, KeyError) as exc:
        if isinstance(exc, ValueError) and str(exc).startswith("depth source"):
            raise
        where = f"folder {name}" if is_folder else f"model {model_id!r}"
        raise ValueError(
            f"depth source 'transformers:{model_id}': the {where} holds no depth-estimation "
            f"model that AutoImageProcessor and AutoModelForDepthEstimation can load "
            f"({_first_line(exc)})"
        ) from None
    net = net.to(device).eval()
    with _LOCK:
        _LOADED[key] = (processor, net)
        while len(_LOADED) > _KEEP_LOADED:
            _LOADED.pop(next(iter(_LOADED)))
    logger.info("loaded %s (%s, %s)", name, type(net).__name__, model_output_kind(net.config))
    return processor, net


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:300]


def _hub_map(model_id: str, image: np.ndarray, device: torch.device) -> tuple[np.ndarray, str]:
    """Run a hub depth model on ``image`` (``H x W x 3`` float in [0, 1]); returns the
    disparity at the photo's size and the kind of output the model gave."""
    from ..io.image import resize_float

    processor, net = _load_hub_model(model_id, device)
    kind = model_output_kind(net.config)
    size = image.shape[:2]
    scale = min(1.0, HUB_MAX_SIDE / max(size))
    small_size = (max(1, round(size[0] * scale)), max(1, round(size[1] * scale)))
    small = resize_float(image, small_size, "bilinear") if scale < 1.0 else image
    pixels = np.round(np.clip(small, 0.0, 1.0) * 255.0).astype(np.uint8)
    inputs = processor(images=pixels, return_tensors="pt")
    inputs = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}
    with torch.no_grad():
        outputs = net(**inputs)
        predicted = _post_process(processor, outputs, small_size)  # [h,w]
    if not bool(torch.isfinite(predicted).any()):
        raise ValueError(f"depth source 'transformers:{model_id}': the model gave no finite depth")
    values = predicted.float().cpu().numpy()
    d = metric_to_disparity(values) if kind == METRIC else relative_to_disparity(values)
    return _fit(d, size), kind


def _post_process(processor: Any, outputs: Any, size: tuple[int, int]) -> torch.Tensor:
    """The model's prediction at ``size`` (``[h, w]``): the processor's own post-processing
    (which undoes its padding and, for Depth Pro, turns inverse depth into metres) where it
    has one, else the raw prediction resized bilinearly."""
    post = getattr(processor, "post_process_depth_estimation", None)
    if post is not None:
        kwargs: dict[str, Any] = {"target_sizes": [size]}
        if "source_sizes" in inspect.signature(post).parameters:
            kwargs["source_sizes"] = [size]
        try:
            out = post(outputs, **kwargs)
            return out[0]["predicted_depth"].reshape(size)
        except (TypeError, ValueError, KeyError, IndexError, RuntimeError) as exc:
            logger.debug("post_process_depth_estimation failed (%s); resizing instead", exc)
    raw = outputs.predicted_depth  # [B,h',w']
    raw = raw.reshape(1, 1, *raw.shape[-2:]).float()
    return F.interpolate(raw, size=size, mode="bilinear", align_corners=False)[0, 0]
