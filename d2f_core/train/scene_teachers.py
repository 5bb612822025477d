"""Scene labels for stage 0 from three more teachers: scene parsing, silhouettes and lines.

``d2f-train label --scene`` runs, beside the VOC and depth teachers of
:mod:`d2f_core.train.teachers`, three TFLite teachers (with ``ai-edge-litert``, training only):

- ``ade``: ADE20K scene parsing (DeepLabV3 + MobileNetV2, 150 classes and "other"), the class
  of every pixel, uint8 at :data:`LABEL_SIDE` on the long side. It knows the sky, the ground
  (floor, road, grass, water, earth...), walls and ceilings, buildings and trees.
- ``sal``: U^2-Net-p's salient-object silhouette, uint8 (0-255, min-max normalised) at
  :data:`LABEL_SIDE`; it finds the main subject of any photo, not only of the VOC classes.
- ``lines``: M-LSD tiny's straight segments, float32 ``N x 5`` (x0, y0, x1, y1 in [0, 1] of
  the width and height, score), for the horizon.

Every array is stored at the photo's own aspect. The teachers never ship: the project's own
network learns from the targets built from these labels (:mod:`d2f_core.train.scene_targets`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

__all__ = ["ADE_FILE", "LABEL_SIDE", "LINES_FILE", "SAL_FILE", "SceneTeachers", "label_size"]

ADE_FILE = "deeplabv3_mobilenetv2_ade20k.tflite"
SAL_FILE = "u2netp_float16.tflite"
LINES_FILE = "mlsd_512_tiny_fp16.tflite"
#: long side of the stored maps (the photos are at most 640 px)
LABEL_SIDE = 256
_ADE_SIDE = 513
_SAL_SIDE = 320
_LINES_SIDE = 512
_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def label_size(width: int, height: int, side: int = LABEL_SIDE) -> tuple[int, int]:
    """``(w, h)`` of a stored map: the photo's aspect with its long side at ``side``."""
    scale = side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


class _Lite:
    """One TFLite graph: ``run(x)`` -> its outputs by name."""

    def __init__(self, path: Path, threads: int) -> None:
        from ai_edge_litert.interpreter import Interpreter

        self.net = Interpreter(model_path=str(path), num_threads=threads)
        self.net.allocate_tensors()
        self.input = self.net.get_input_details()[0]["index"]
        self.outputs = {o["name"]: o["index"] for o in self.net.get_output_details()}

    def run(self, x: np.ndarray) -> dict[str, np.ndarray]:
        self.net.set_tensor(self.input, x)
        self.net.invoke()
        return {name: self.net.get_tensor(i) for name, i in self.outputs.items()}


class SceneTeachers:
    """The scene-parsing, silhouette and line teachers of ``folder``.

    ``teachers(rgb, saliency=True)`` -> ``{"ade", "sal", "lines"}`` for a PIL RGB photo (the
    silhouette is skipped, and absent from the result, when ``saliency`` is False: photos
    with a human mask do not need it).
    """

    def __init__(self, folder: str | Path, threads: int = 1) -> None:
        folder = Path(folder)
        self.ade = _Lite(folder / ADE_FILE, threads)
        self.sal = _Lite(folder / SAL_FILE, threads)
        self.lines = _Lite(folder / LINES_FILE, threads)

    def parse(self, rgb: Image.Image) -> np.ndarray:
        """ADE20K class per pixel, uint8 at :func:`label_size`."""
        w, h = rgb.size
        s = _ADE_SIDE / max(w, h)
        rw, rh = max(1, round(w * s)), max(1, round(h * s))
        x = np.zeros((_ADE_SIDE, _ADE_SIDE, 3), np.float32)  # padding is mid-grey, 0
        x[:rh, :rw] = np.asarray(rgb.resize((rw, rh), Image.BILINEAR), np.float32) / 127.5 - 1
        logits = next(iter(self.ade.run(x[None]).values()))[0, :rh, :rw]  # [rh, rw, 151]
        cls = logits.argmax(axis=-1).astype(np.uint8)
        return np.asarray(Image.fromarray(cls).resize(label_size(w, h), Image.NEAREST))

    def silhouette(self, rgb: Image.Image) -> np.ndarray:
        """Salient-object probability, uint8 (0-255) at :func:`label_size`."""
        w, h = rgb.size
        x = np.asarray(rgb.resize((_SAL_SIDE, _SAL_SIDE), Image.BILINEAR), np.float32) / 255
        x = (x - _IMAGENET_MEAN) / _IMAGENET_STD
        out = self.sal.run(x[None].astype(np.float32))
        m = out.get("Identity", next(iter(out.values())))[0, ..., 0]
        lo, hi = float(m.min()), float(m.max())
        m = (m - lo) / max(hi - lo, 1e-6)
        img = Image.fromarray(np.round(m * 255).astype(np.uint8))
        return np.asarray(img.resize(label_size(w, h), Image.BILINEAR))

    def segments(self, rgb: Image.Image, min_score: float = 0.1) -> np.ndarray:
        """Line segments, float32 ``N x 5``: x0, y0, x1, y1 as fractions of the width and
        height, and the score; segments shorter than 20 px of the 512-px input are dropped."""
        x = np.ones((_LINES_SIDE, _LINES_SIDE, 4), np.float32)
        x[..., :3] = np.asarray(rgb.resize((_LINES_SIDE, _LINES_SIDE), Image.BILINEAR))
        out = self.lines.run(x[None])
        centres = out["Identity"][0].astype(np.float32)  # [200, 2] (y, x) on the 256 grid
        scores = out["Identity_1"][0].astype(np.float32)
        disp = out["Identity_2"][0]  # [256, 256, 4]
        rows = []
        for (cy, cx), score in zip(centres, scores, strict=True):
            if score <= min_score:
                continue
            iy, ix = int(np.clip(cy, 0, 255)), int(np.clip(cx, 0, 255))
            dx0, dy0, dx1, dy1 = disp[iy, ix]
            x0, y0 = (cx + dx0) * 2, (cy + dy0) * 2
            x1, y1 = (cx + dx1) * 2, (cy + dy1) * 2
            if np.hypot(x1 - x0, y1 - y0) < 20:
                continue
            rows.append([x0, y0, x1, y1, score])
        seg = np.array(rows, np.float32).reshape(-1, 5)
        seg[:, :4] = np.clip(seg[:, :4] / _LINES_SIDE, 0.0, 1.0)
        return seg

    def __call__(self, rgb: Image.Image, saliency: bool = True) -> dict[str, np.ndarray]:
        out = {"ade": self.parse(rgb), "lines": self.segments(rgb)}
        if saliency:
            out["sal"] = self.silhouette(rgb)
        return out


def _interleaved(photos: list) -> list:
    """The photos taken round-robin over their sources, so that any first part of the list
    (labels written so far) holds every kind of photo in proportion: a source's k-th photo
    comes at the fraction (k + 0.5) / its count of the way."""
    by_source: dict[str, list] = {}
    for p in photos:
        by_source.setdefault(p.source, []).append(p)
    queues = sorted(by_source.values(), key=len, reverse=True)
    keyed = [((k + 0.5) / len(q), i, p) for i, q in enumerate(queues) for k, p in enumerate(q)]
    return [p for _, _, p in sorted(keyed, key=lambda t: (t[0], t[1]))]


def label_scene_photos(
    root: str | Path,
    out: str | Path,
    teachers: str | Path | None = None,
    threads: int = 1,
    shard: tuple[int, int] = (0, 1),
    heldout: bool = False,
) -> int:
    """Write one ``.npz`` per photo of ``root`` with every teacher's label: ``fg`` and
    ``depth`` (:class:`d2f_core.train.teachers.Teachers`), ``ade``, ``lines`` and, for photos
    without a human mask, ``sal`` (:class:`SceneTeachers`).

    Photos already labelled in ``out`` are skipped, so a killed run resumes; each file is
    written under a temporary name and renamed. ``shard = (i, n)`` labels every n-th photo
    from the i-th, for ``n`` processes side by side. Held-out photos are skipped unless
    ``heldout``. Returns the number labelled in this call.
    """
    from .heldout import is_heldout
    from .teachers import Teachers, iter_photos, write_labels

    root = Path(root)
    folder = Path(teachers) if teachers is not None else root / "teachers"
    photos = [p for p in iter_photos(root) if heldout or not is_heldout(p)]
    index, count = shard
    old, new = Teachers(folder, threads), SceneTeachers(folder, threads)

    def label(photo, rgb: Image.Image) -> dict[str, np.ndarray]:
        fg, depth = old(rgb)
        return {"fg": fg, "depth": depth, **new(rgb, saliency=photo.mask is None)}

    return write_labels(_interleaved(photos)[index::count], Path(out), label, log_every=50)


def run_label_scene(argv=None) -> int:
    """``d2f-train label-scene ROOT --out DIR [--shard I/N]``: :func:`label_scene_photos`."""
    import argparse
    import logging

    from .teachers import shard_arg

    p = argparse.ArgumentParser(
        prog="d2f-train label-scene",
        description="label real photos with every teacher (VOC, depth, ADE20K, U^2-Net-p, M-LSD)",
    )
    p.add_argument("root", type=Path, help="datasets folder (e.g. ../shared/datasets)")
    p.add_argument("--out", type=Path, required=True, help="folder for the .npz labels")
    p.add_argument("--teachers", type=Path, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument(
        "--shard", type=shard_arg, default=(0, 1), metavar="I/N",
        help="every N-th photo from the I-th",
    )  # fmt: skip
    p.add_argument("--heldout", action="store_true", help="label the held-out photos too")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    done = label_scene_photos(
        args.root, args.out, args.teachers, args.threads, args.shard, args.heldout
    )
    print(f"labelled {done} photos into {args.out}")
    return 0
