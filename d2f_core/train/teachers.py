"""Pseudo-labels for real photos from small pretrained teachers (training time only).

``d2f-train label`` runs two teachers over a folder of photos laid out like
``../shared/datasets`` and writes one ``.npz`` per photo:

- ``fg``: the VOC segmentation teacher's foreground probability ``1 - P(background)``,
  uint8 (0-255) at 257x257 (DeepLabV3 + MobileNetV2, 21 PASCAL VOC classes, ONNX, run with
  ``onnxruntime``);
- ``depth``: the indoor depth teacher's raw output, uint8 at 224x224, metres = 0.0717 x value
  (FastDepth, full-integer TFLite, run with ``ai-edge-litert``).

The teachers and their runtimes are never part of the package: ``onnxruntime`` and
``ai-edge-litert`` are needed only here (``pip install -e ".[teach]"``). What ships is the
project's own network, trained with these labels (see :mod:`d2f_core.train.depth_train`).
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

__all__ = [
    "FeatureTeacher",
    "Photo",
    "Teachers",
    "iter_photos",
    "label_maps",
    "label_photos",
    "mask_box",
    "read_label",
    "read_mask",
    "run_label",
    "shard_arg",
    "subject_cutout",
    "write_labels",
]

logger = logging.getLogger(__name__)

#: folders of ``../shared/datasets`` with human-drawn masks, and how their masks read
MASKED_SOURCES = {
    "salient/ecssd": "binary",
    "salient/davis": "binary",
    "salient/coco128": "coco",
}
#: folders of photos without masks
PLAIN_SOURCES = (
    "photos/imagenet_sample",
    "photos/sun_hays80",
    "photos/urban100",
    "photos/bsds500",
)
_IMAGE_EXTS = {".jpg", ".jpeg", ".png"}
#: COCO panoptic ids below this are "thing" classes (objects), the rest "stuff" (sky, wall)
COCO_FIRST_STUFF = 92


@dataclass(frozen=True)
class Photo:
    """One training photo: its path, its source folder, and its mask (``None`` if none)."""

    path: Path
    source: str
    mask: Path | None
    mask_kind: str | None

    @property
    def key(self) -> str:
        return f"{self.source.replace('/', '__')}__{self.path.stem}"


def iter_photos(root: str | Path) -> Iterator[Photo]:
    """Every photo under ``root`` (a ``../shared/datasets``-like folder), sorted per source."""
    root = Path(root)
    for source, kind in MASKED_SOURCES.items():
        folder = root / source / "images"
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if path.suffix.lower() not in _IMAGE_EXTS:
                continue
            mask = root / source / "masks" / f"{path.stem}.png"
            yield Photo(path, source, mask if mask.is_file() else None, kind)
    for source in PLAIN_SOURCES:
        folder = root / source
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if path.suffix.lower() in _IMAGE_EXTS:
                yield Photo(path, source, None, None)


def read_mask(photo: Photo, size: tuple[int, int]) -> np.ndarray | None:
    """The photo's human-drawn subject mask as float32 ``H x W`` in {0, 1} at ``size``
    (``(H, W)``), or ``None``. COCO class maps count every "thing" class as subject."""
    if photo.mask is None:
        return None
    with Image.open(photo.mask) as im:
        im = im.convert("L") if photo.mask_kind == "binary" else im
        arr = np.asarray(im)
    if arr.ndim == 3:
        arr = arr[..., 0]
    if photo.mask_kind == "coco":
        sub = (arr > 0) & (arr < COCO_FIRST_STUFF)
    else:
        sub = arr > 127
    if sub.shape != size:
        sub = (
            np.asarray(
                Image.fromarray(sub.astype(np.uint8) * 255).resize(
                    (size[1], size[0]), Image.NEAREST
                )
            )
            > 127
        )
    return sub.astype(np.float32)


def subject_cutout(photo: Photo) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The photo's subject cut out to its bounding box: ``(rgb, mask, coverage)``, the photo
    as float32 ``h x w x 3`` in [0, 1], its mask ``h x w`` in {0, 1}, and the share of the
    whole photo the subject covers; ``None`` for a photo without a mask or with an empty one.
    """
    from ..io import load_image

    if photo.mask is None:
        return None
    rgb = load_image(photo.path)
    mask = read_mask(photo, rgb.shape[:2])
    if not mask.any():
        return None
    box = mask_box(mask)
    return rgb[box], mask[box], float(mask.mean())


def mask_box(mask: np.ndarray) -> tuple[slice, slice]:
    """The bounding box of a mask's non-zero pixels (the mask must have one)."""
    ys, xs = np.nonzero(mask)
    return slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1)


def shard_arg(text: str) -> tuple[int, int]:
    """``--shard I/N`` (every N-th photo from the I-th) as ``(I, N)``, for argparse."""
    try:
        i, n = (int(v) for v in text.split("/"))
        if not 0 <= i < n:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--shard must be I/N with 0 <= I < N, got {text!r}"
        ) from None
    return i, n


class Teachers:
    """The two labelling teachers: ``teachers(rgb)`` -> ``(fg, depth)`` as stored in a label
    file (uint8 VOC foreground at 257x257, uint8 depth at 224x224)."""

    def __init__(self, teachers: Path, threads: int) -> None:
        import onnxruntime as ort
        from ai_edge_litert.interpreter import Interpreter

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self.seg = ort.InferenceSession(
            str(teachers / "deeplabv3_mobilenetv2_voc.onnx"),
            sess_options=opts,
            providers=["CPUExecutionProvider"],
        )
        self.seg_input = self.seg.get_inputs()[0].name
        self.depth = Interpreter(
            model_path=str(teachers / "fast_depth_224_int8.tflite"), num_threads=threads
        )
        self.depth.allocate_tensors()
        self.depth_in = self.depth.get_input_details()[0]["index"]
        self.depth_out = self.depth.get_output_details()[0]["index"]

    def __call__(self, rgb: Image.Image) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(rgb.resize((257, 257), Image.BILINEAR), dtype=np.float32)
        x = x[None] / 127.5 - 1.0
        logits = self.seg.run(None, {self.seg_input: x})[0][0]  # [257,257,21]
        logits = logits - logits.max(axis=-1, keepdims=True)
        p = np.exp(logits)
        fg = 1.0 - p[..., 0] / p.sum(axis=-1)
        d_in = np.asarray(rgb.resize((224, 224), Image.BILINEAR), dtype=np.uint8)[None]
        self.depth.set_tensor(self.depth_in, d_in)
        self.depth.invoke()
        depth = self.depth.get_tensor(self.depth_out)[0, ..., 0]
        return np.round(fg * 255).astype(np.uint8), depth.astype(np.uint8)


#: the VOC teacher's 256-channel features after its ASPP projection (stride 8, 33x33 at 257)
SEG_FEATURES = "Relu__94:0"
SEG_SIDE = 257


class FeatureTeacher:
    """Intermediate features of an ONNX teacher, for feature distillation in stage 0.

    The graph is loaded with ``onnx``, the tensor named ``output`` is made one of its
    outputs, and ``onnxruntime`` runs it on one thread (the teacher runs inside a data-loading
    process). For the VOC teacher the default output is the 256-channel feature map that its
    classifier reads: the network learns to hold what the teacher knows of objects, which
    labels alone (its foreground probability) pass on only in part.

    Args:
        path: the ONNX file.
        output: name of the tensor to return.
        side: the square input side the graph takes (inputs are resized to it); the graph
            takes channels last, as the VOC teacher does.
    """

    def __init__(
        self,
        path: str | Path,
        output: str = SEG_FEATURES,
        side: int = SEG_SIDE,
        threads: int = 1,
    ) -> None:
        import onnx
        import onnxruntime as ort

        model = onnx.load(str(path))
        produced = {name for node in model.graph.node for name in node.output}
        if output not in produced:
            raise ValueError(f"{path}: no tensor named {output!r} in the graph")
        del model.graph.output[:]
        model.graph.output.append(
            onnx.helper.make_tensor_value_info(output, onnx.TensorProto.FLOAT, None)
        )
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(
            model.SerializeToString(), sess_options=opts, providers=["CPUExecutionProvider"]
        )
        self.input = self.session.get_inputs()[0].name
        self.side = side

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Features of a batch: ``images`` float ``B x H x W x 3`` in [0, 1] (each resized to
        the teacher's square input and scaled to [-1, 1]) -> float32 ``B x C x h x w``."""
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"images must be B x H x W x 3, got shape {images.shape}")
        t = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)).permute(0, 3, 1, 2)
        t = F.interpolate(t, size=(self.side, self.side), mode="bilinear", align_corners=False)
        x = (t * 2.0 - 1.0).permute(0, 2, 3, 1)
        feats = [
            self.session.run(None, {self.input: x[i : i + 1].numpy()})[0] for i in range(len(x))
        ]
        return np.concatenate(feats, axis=0).astype(np.float32)


def write_labels(
    photos: Iterable[Photo],
    out: Path,
    label: Callable[[Photo, Image.Image], dict[str, np.ndarray]],
    log_every: int = 200,
) -> int:
    """Write ``label(photo, rgb)``'s arrays to ``out/<key>.npz`` for each photo that has no
    label there yet (so a killed run resumes), each file under a temporary name and renamed.

    Returns the number of photos labelled in this call. A photo that cannot be read is
    logged and skipped.
    """
    out.mkdir(parents=True, exist_ok=True)
    done = 0
    t0 = time.perf_counter()
    for photo in photos:
        dst = out / f"{photo.key}.npz"
        if dst.is_file():
            continue
        try:
            with Image.open(photo.path) as im:
                rgb = im.convert("RGB")
        except OSError as exc:
            logger.warning("%s: unreadable, skipped (%s)", photo.path, exc)
            continue
        tmp = dst.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **label(photo, rgb))
        tmp.replace(dst)
        done += 1
        if done % log_every == 0:
            logger.info("labelled %d photos (%.1f s)", done, time.perf_counter() - t0)
    return done


def label_photos(
    root: str | Path, out: str | Path, teachers: str | Path | None = None, threads: int = 2
) -> int:
    """Run the teachers over every photo of ``root`` that has no label in ``out`` yet
    (:func:`write_labels`); returns the number of photos labelled in this call."""
    root = Path(root)
    net = Teachers(Path(teachers) if teachers is not None else root / "teachers", threads)

    def label(photo: Photo, rgb: Image.Image) -> dict[str, np.ndarray]:
        fg, depth = net(rgb)
        return {"fg": fg, "depth": depth}

    return write_labels(iter_photos(root), Path(out), label)


def read_label(path: str | Path, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`label_maps` of a label file written by :func:`label_photos`."""
    with np.load(path) as z:
        return label_maps(z["fg"], z["depth"], size)


def label_maps(
    fg: np.ndarray, depth: np.ndarray, size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """``(fg, disparity)`` of the teachers' raw outputs resized to ``size`` (``(H, W)``),
    float32.

    ``fg`` is the foreground probability in [0, 1]; ``disparity`` is ``1 / depth`` of the depth
    teacher smoothed by a Gaussian of 4 px at its 224-px output, rank-normalised to [0, 1]
    (1 = nearest).
    """
    from ..depth.layout import teacher_disparity

    h, w = size
    fg_i = Image.fromarray(fg).resize((w, h), Image.BILINEAR)
    return np.asarray(fg_i, dtype=np.float32) / 255.0, teacher_disparity(depth, size)


def run_label(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="d2f-train label", description="pseudo-label real photos with the teachers"
    )
    parser.add_argument("root", type=Path, help="datasets folder (e.g. ../shared/datasets)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the .npz labels")
    parser.add_argument("--teachers", type=Path, default=None)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    n = label_photos(args.root, args.out, args.teachers, args.threads)
    print(f"labelled {n} photos into {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_label())
