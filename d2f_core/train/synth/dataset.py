"""Training pairs, the EBB!-format writer and the ``d2f-synth`` CLI."""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ...errors import whole_number
from .lens import Scene, linear_to_srgb, render_pinhole, render_thin_lens
from .scene import builtin_textures, describe_layers, load_textures, make_scene

logger = logging.getLogger(__name__)

#: ``scene_fn(size, seed, margin) -> Scene``: a scene maker other than :func:`make_scene`
SceneFn = Callable[[tuple[int, int], int, int], Scene]


@dataclass
class SynthPair:
    """A generated training pair.

    Attributes:
        image: pinhole view, float32 ``(H, W, 3)`` in [0, 1], in ``encoding``.
        bokeh: thin-lens view, float32 ``(H, W, 3)`` in [0, 1], in ``encoding``.
        disparity: front-most opaque layer's disparity, float32 ``(H, W)`` in [0, 1].
        params: JSON-able render parameters (focus, blur, samples, seed, size, layers, ...).
    """

    image: np.ndarray
    bokeh: np.ndarray
    disparity: np.ndarray
    params: dict


# --------------------------------------------------------------------------- pairs


def _encode(radiance: np.ndarray, encoding: str) -> np.ndarray:
    clipped = np.clip(radiance, 0.0, 1.0).astype(np.float32)
    return linear_to_srgb(clipped) if encoding == "srgb" else clipped


def make_pair(
    size: tuple[int, int] = (512, 512),
    *,
    seed: int,
    focus: float | None = None,
    blur: float | None = None,
    samples: int = 256,
    subject_share: float = 0.7,
    blur_fraction: float = 0.06,
    encoding: str = "srgb",
    textures: Sequence[np.ndarray] | None = None,
    device: torch.device | str | None = None,
    scene_fn: SceneFn | None = None,
) -> SynthPair:
    """One pinhole / thin-lens training pair with its disparity.

    Unless ``focus`` and ``blur`` are given, a share ``subject_share`` of seeds focuses on the
    main subject at ``K = blur_fraction * max(size)`` (like EBB!: one lens, subject sharp);
    the rest use a random focal plane (uniform, or a random layer's disparity) and a random
    ``K`` in ``[0.02, 0.12] * max(size)``.

    ``scene_fn(size, seed, margin)``, when given, makes the scene instead of
    :func:`make_scene` (for example :class:`~d2f_core.train.synth.photo.PhotoScenes`).

    Returns:
        :class:`SynthPair`; ``params["blur"]`` is K in px at ``size``.
    """
    if encoding not in ("srgb", "linear"):
        raise ValueError(f"encoding must be 'srgb' or 'linear', got {encoding!r}")
    if not 0.0 <= subject_share <= 1.0:
        raise ValueError(f"subject_share must be in [0, 1], got {subject_share!r}")
    samples = whole_number(samples, "samples", 1)
    rng = np.random.default_rng([int(seed), 0x5EED])  # focus/blur draws, apart from the scene's
    long_side = max(size)
    mode = "subject" if rng.random() < subject_share else "random"
    if blur is None:
        frac = blur_fraction if mode == "subject" else rng.uniform(0.02, 0.12)
        blur = round(float(frac * long_side), 3)
    if blur < 0:
        raise ValueError(f"blur must be >= 0, got {blur!r}")
    margin = math.ceil(blur / 2) + 2
    if scene_fn is None:
        scene = make_scene(size, seed=seed, margin=margin, textures=textures)
    else:
        scene = scene_fn(size, seed, margin)
    if focus is None:
        if mode == "subject":
            focus = scene.subject
        elif rng.random() < 0.5:
            focus = rng.uniform(0.0, 1.0)
        else:
            focus = scene.layers[rng.integers(len(scene.layers))].order
        focus = float(np.clip(focus, 0.0, 1.0))
    else:
        mode = "given"
    pinhole, disparity = render_pinhole(scene)
    bokeh = render_thin_lens(scene, focus, blur, samples=samples, device=device)
    params = {
        "focus": round(float(focus), 6),
        "blur": float(blur),
        "samples": int(samples),
        "seed": int(seed),
        "size": [int(size[0]), int(size[1])],
        "mode": mode,
        "encoding": encoding,
        "margin": scene.margin,
        "layers": describe_layers(scene.layers),
    }
    return SynthPair(_encode(pinhole, encoding), _encode(bokeh, encoding), disparity, params)


def _save_rgb(path: Path, img: np.ndarray, fmt: str) -> None:
    from PIL import Image

    data = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    if fmt == "jpg":
        Image.fromarray(data).save(path, quality=95, subsampling=0)
    else:
        Image.fromarray(data).save(path)


def generate_dataset(
    root: str | Path,
    n: int,
    *,
    seed: int,
    size: tuple[int, int] = (512, 512),
    samples: int = 256,
    fmt: str = "png",
    start_id: int = 0,
    id_width: int = 5,
    subject_share: float = 0.7,
    blur_fraction: float = 0.06,
    encoding: str = "srgb",
    textures: Sequence[np.ndarray] | None = None,
    device: torch.device | str | None = None,
    scene_fn: SceneFn | None = None,
) -> list[str]:
    """Write ``n`` pairs in EBB! layout and return their ids.

    ``root/original/<id>.<fmt>`` (pinhole input), ``root/bokeh/<id>.<fmt>`` (thin-lens
    target), ``root/disparity/<id>.png`` (16-bit, ``round(d * 65535)``, 1 = nearest) and
    ``root/params/<id>.json``. Ids are ``start_id, start_id + 1, ...`` zero-padded to
    ``id_width``; pair ``i`` uses a seed derived from ``(seed, id)``, stored in its JSON, so
    :func:`make_pair` with that seed regenerates it.
    """
    from PIL import Image

    if fmt not in ("png", "jpg"):
        raise ValueError(f"fmt must be 'png' or 'jpg', got {fmt!r}")
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be a non-negative integer, got {n!r}")
    if start_id < 0:
        raise ValueError(f"start_id must be >= 0, got {start_id!r}")
    root = Path(root)
    for sub in ("original", "bokeh", "disparity", "params"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    ids = []
    for idx in range(start_id, start_id + n):
        pid = f"{idx:0{id_width}d}"
        pair_seed = int(np.random.SeedSequence([int(seed), idx]).generate_state(1)[0])
        t0 = time.perf_counter()
        pair = make_pair(
            size,
            seed=pair_seed,
            samples=samples,
            subject_share=subject_share,
            blur_fraction=blur_fraction,
            encoding=encoding,
            textures=textures,
            device=device,
            scene_fn=scene_fn,
        )
        _save_rgb(root / "original" / f"{pid}.{fmt}", pair.image, fmt)
        _save_rgb(root / "bokeh" / f"{pid}.{fmt}", pair.bokeh, fmt)
        disp16 = np.round(np.clip(pair.disparity, 0, 1) * 65535).astype(np.uint16)
        Image.fromarray(disp16).save(root / "disparity" / f"{pid}.png")
        params = pair.params | {"id": pid, "dataset_seed": int(seed)}
        (root / "params" / f"{pid}.json").write_text(json.dumps(params, indent=1))
        logger.info(
            "pair %s: focus %.3f, K %.1f px, %.2f s",
            pid,
            pair.params["focus"],
            pair.params["blur"],
            time.perf_counter() - t0,
        )
        ids.append(pid)
    return ids


def _parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 512x512, got {text!r}") from None
    if min(h, w) < 16:
        raise argparse.ArgumentTypeError(f"size must be at least 16x16, got {text!r}")
    return h, w


def main(argv: list[str] | None = None) -> int:
    """``d2f-synth OUT --count N --seed S --size HxW --samples N [--format png|jpg]``."""
    parser = argparse.ArgumentParser(
        prog="d2f-synth",
        description="Generate synthetic EBB!-format bokeh pairs with exact thin-lens targets.",
    )
    parser.add_argument("out", type=Path, help="output folder")
    parser.add_argument("--count", type=int, default=10, help="pairs to write")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=_parse_size, default=(512, 512), help="HxW")
    parser.add_argument("--samples", type=int, default=256, help="aperture samples")
    parser.add_argument("--format", choices=("png", "jpg"), default="png")
    parser.add_argument("--start-id", type=int, default=0)
    parser.add_argument("--subject-share", type=float, default=0.7)
    parser.add_argument(
        "--blur-fraction",
        type=float,
        default=0.06,
        help="K of the subject-focused pairs, as a fraction of the long side",
    )
    parser.add_argument("--encoding", choices=("srgb", "linear"), default="srgb")
    parser.add_argument(
        "--textures",
        type=Path,
        default=None,
        help="extra folder of texture photos (added to the scikit-image ones)",
    )
    parser.add_argument(
        "--photos",
        type=Path,
        default=None,
        metavar="DATASETS",
        help="make the scenes of real photos from this datasets folder (cut-out subjects on "
        "photo backgrounds, d2f_core.train.synth.photo) instead of generated shapes",
    )
    parser.add_argument(
        "--photo-split",
        choices=("heldout", "train"),
        default="heldout",
        help="with --photos: the photos depth training never sees, or the others",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    if args.verbose:
        logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.count < 0 or args.samples < 1 or args.start_id < 0:
        parser.error("--count and --start-id must be >= 0 and --samples >= 1")
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        textures = None
        if args.textures is not None:
            textures = list(builtin_textures()) + load_textures(args.textures)
        scene_fn = None
        if args.photos is not None:
            from .photo import PhotoScenes

            scene_fn = PhotoScenes(args.photos, split=args.photo_split)
        generate_dataset(
            args.out,
            args.count,
            seed=args.seed,
            size=args.size,
            samples=args.samples,
            fmt=args.format,
            start_id=args.start_id,
            subject_share=args.subject_share,
            blur_fraction=args.blur_fraction,
            encoding=args.encoding,
            textures=textures,
            scene_fn=scene_fn,
        )
    except (ValueError, TypeError, OSError) as err:
        logging.getLogger(__name__).error("d2f-synth: %s", err)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
