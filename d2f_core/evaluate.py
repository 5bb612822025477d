"""``d2f-eval``: PSNR / SSIM / runtime of D2F (or a baseline) on an EBB!-format split.

``d2f-eval DATA --weights CKPT --out DIR [--split val470]`` writes ``DIR/eval_<split>.csv``
(``id, psnr, ssim, ms``) and prints the means. ``--fusion`` instead compares ways of joining
the sharp input ``I_hr`` with the upsampled low-res bokeh ``B_up`` (all from the same render),
writing ``DIR/fusion_<split>.csv`` (``id, method, psnr, ssim, ms``):

* ``upsample``: ``B_up`` alone (no fusion);
* ``alpha``: naive alpha blending with the binary mask ``M_b = D < theta`` (theta = 0.25);
* ``poisson``: naive Poisson blending (gradients of ``I_hr`` inside ``M_b``, ``B_up`` on its
  boundary; sparse solve with scipy, imported only here);
* ``laplacian``: Laplacian-pyramid blending of ``I_hr`` and ``B_up`` under ``M_b``;
* ``deep``: the model's deep Poisson fusion (``M = max(M_s, in-focus prior)``).

``--baseline identity`` (the input itself) and ``--baseline gaussian`` (a global Gaussian
blur) need no weights. Focus and blur come from each pair's params file, else from the
model config's training defaults (EBB!: focus 1.0, K = 138 px at 1024x1536). ``--focus-by``
chooses the focus otherwise: ``click`` reads the model's map where the pair is sharp,
``subject`` and ``subject-range`` focus where the app and the CLI do with no focus given
(the search counts in ``ms``); the blur still comes from the pair.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import metrics
from .pipeline import D2F, D2FConfig
from .rendering.schedule import coc_to_defocus
from .train.data import EBBDataset

__all__ = [
    "FUSION_METHODS",
    "alpha_blend",
    "click_focus",
    "disparity_errors",
    "gaussian_background_baseline",
    "gaussian_baseline",
    "laplacian_pyramid_blend",
    "main",
    "poisson_blend",
]

logger = logging.getLogger(__name__)

FUSION_METHODS = ("upsample", "alpha", "poisson", "laplacian", "deep")


def _check_triplet(image: np.ndarray, bokeh: np.ndarray, mask: np.ndarray) -> None:
    if image.ndim != 3 or image.shape[2] != 3 or image.shape != bokeh.shape:
        raise ValueError(
            f"image {image.shape} and bokeh {bokeh.shape} must both be H x W x 3 of one size"
        )
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask must be H x W = {image.shape[:2]}, got {mask.shape}")


def alpha_blend(image: np.ndarray, bokeh: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``mask * image + (1 - mask) * bokeh``. Shapes: HxWx3, HxWx3, HxW -> HxWx3 float32."""
    _check_triplet(image, bokeh, mask)
    m = mask[..., None].astype(np.float32)
    return (m * image + (1 - m) * bokeh).astype(np.float32)


def poisson_blend(image: np.ndarray, bokeh: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Naive Poisson blending: inside ``mask`` solve ``lap(f) = lap(image)`` with ``f = bokeh``
    on the mask's outer boundary; outside it ``f = bokeh``. Image borders are Neumann.

    Shapes: HxWx3, HxWx3, HxW (bool or {0, 1}) -> HxWx3 float32, clipped to [0, 1].
    """
    import scipy.sparse
    import scipy.sparse.linalg

    _check_triplet(image, bokeh, mask)
    inside = np.asarray(mask) > 0.5
    out = bokeh.astype(np.float64).copy()
    n = int(inside.sum())
    if n == 0:
        return out.astype(np.float32)
    if n == inside.size:
        return image.astype(np.float32)  # no boundary: the guidance field is the image
    h, w = inside.shape
    index = -np.ones((h, w), dtype=np.int64)
    ys, xs = np.nonzero(inside)
    index[ys, xs] = np.arange(n)
    g = image.astype(np.float64)
    rows, cols, vals = [np.arange(n)], [np.arange(n)], []
    diag = np.zeros(n)
    rhs = np.zeros((n, 3))
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ny, nx = ys + dy, xs + dx
        valid = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
        p = np.nonzero(valid)[0]
        qy, qx = ny[valid], nx[valid]
        diag[p] += 1
        rhs[p] += g[ys[p], xs[p]] - g[qy, qx]  # guidance: gradients of the sharp image
        q_index = index[qy, qx]
        unknown = q_index >= 0
        rows.append(p[unknown])
        cols.append(q_index[unknown])
        vals.append(-np.ones(int(unknown.sum())))
        known = ~unknown
        rhs[p[known]] += out[qy[known], qx[known]]  # Dirichlet boundary from B_up
    data = np.concatenate([diag, *vals])
    matrix = scipy.sparse.csc_matrix(
        (data, (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    solve = scipy.sparse.linalg.factorized(matrix)
    for c in range(3):
        out[ys, xs, c] = solve(rhs[:, c])
    return np.clip(out, 0, 1).astype(np.float32)


def _pyr_down(x: torch.Tensor) -> torch.Tensor:
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=x.dtype) / 16
    k2 = (k[:, None] * k[None, :]).expand(x.shape[1], 1, 5, 5)
    return F.conv2d(F.pad(x, (2, 2, 2, 2), mode="replicate"), k2, groups=x.shape[1])[..., ::2, ::2]


def _pyr_up(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


def laplacian_pyramid_blend(
    image: np.ndarray, bokeh: np.ndarray, mask: np.ndarray, levels: int = 5
) -> np.ndarray:
    """Laplacian-pyramid blending (Burt and Adelson): each band of ``image`` and ``bokeh`` is
    blended with the Gaussian pyramid of ``mask``; the coarsest level is blended directly.

    Shapes: HxWx3, HxWx3, HxW in [0, 1] -> HxWx3 float32 in [0, 1].
    """
    _check_triplet(image, bokeh, mask)
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    a = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
    b = torch.from_numpy(np.ascontiguousarray(bokeh, np.float32)).permute(2, 0, 1)[None]
    m = torch.from_numpy(np.ascontiguousarray(mask, np.float32))[None, None]
    ga, gb, gm = [a], [b], [m]
    for _ in range(levels - 1):
        if min(ga[-1].shape[-2:]) < 4:
            break
        ga.append(_pyr_down(ga[-1]))
        gb.append(_pyr_down(gb[-1]))
        gm.append(_pyr_down(gm[-1]))
    out = gm[-1] * ga[-1] + (1 - gm[-1]) * gb[-1]
    for level in range(len(ga) - 2, -1, -1):
        size = tuple(ga[level].shape[-2:])
        la = ga[level] - _pyr_up(ga[level + 1], size)
        lb = gb[level] - _pyr_up(gb[level + 1], size)
        out = _pyr_up(out, size) + gm[level] * la + (1 - gm[level]) * lb
    return out[0].permute(1, 2, 0).clamp(0, 1).numpy()


def gaussian_baseline(image: np.ndarray, sigma: float = 3.0) -> np.ndarray:
    """Global Gaussian blur (a trivial bokeh baseline). Shape: HxWx3 -> HxWx3 float32."""
    if sigma <= 0:
        return image.astype(np.float32)
    radius = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    k = torch.exp(-(x**2) / (2 * sigma**2))
    k = k / k.sum()
    t = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
    t = F.pad(t, (radius, radius, radius, radius), mode="replicate")
    t = F.conv2d(t, k.view(1, 1, 1, -1).expand(3, 1, 1, -1), groups=3)
    t = F.conv2d(t, k.view(1, 1, -1, 1).expand(3, 1, -1, 1), groups=3)
    return t[0].permute(1, 2, 0).numpy()


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------


def _focus_blur(item: dict, config: D2FConfig) -> tuple[float, float]:
    focus, blur = float(item["focus"]), float(item["blur"])
    return (
        config.train_focus if math.isnan(focus) else focus,
        config.train_blur if math.isnan(blur) else blur,
    )


def disparity_errors(pred: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Agreement of a predicted disparity map with ground truth, blind to scale and shift.

    Returns ``(spearman, si_rmse)``: the Spearman rank correlation, and the RMSE after the
    least-squares fit ``a * pred + b`` to ``target`` (both maps in [0, 1]).
    """
    p = np.asarray(pred, np.float64).ravel()
    t = np.asarray(target, np.float64).ravel()
    if p.shape != t.shape:
        raise ValueError(f"pred {np.shape(pred)} and target {np.shape(target)} differ in shape")
    design = np.stack([p, np.ones_like(p)], axis=1)
    coef, *_ = np.linalg.lstsq(design, t, rcond=None)
    si_rmse = float(np.sqrt(np.mean((design @ coef - t) ** 2)))
    if p.std() == 0 or t.std() == 0:
        return 0.0, si_rmse
    rank_p = np.argsort(np.argsort(p, kind="stable"), kind="stable").astype(np.float64)
    rank_t = np.argsort(np.argsort(t, kind="stable"), kind="stable").astype(np.float64)
    return float(np.corrcoef(rank_p, rank_t)[0, 1]), si_rmse


def gaussian_background_baseline(
    image: np.ndarray, disparity: np.ndarray, focus: float, blur: float
) -> np.ndarray:
    """Keep pixels within 1 px of CoC sharp, blur the rest with one Gaussian (sigma = K / 8).

    The plain "portrait mode" recipe, given the true disparity. Shape: HxWx3 -> HxWx3.
    """
    coc = blur * np.abs(disparity - focus)
    sharp = np.clip(2.0 - coc, 0.0, 1.0)[..., None]  # 1 below 1 px, 0 above 2 px
    blurred = gaussian_baseline(image, max(blur / 8.0, 0.5))
    return (sharp * image + (1 - sharp) * blurred).astype(np.float32)


def click_focus(
    predicted: np.ndarray, true: np.ndarray, focus: float, tolerance: float = 0.02
) -> float:
    """The predicted disparity where the true map is in focus (median over the pixels within
    ``tolerance`` of ``focus``): what clicking the sharp part of the target would pick.
    ``focus`` itself when no pixel is that close (a focal plane between the objects)."""
    near = np.abs(true - focus) < tolerance
    if not near.any():
        return float(focus)
    return float(np.clip(np.median(predicted[near]), 0.0, 1.0))


def _score(pred: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    return metrics.psnr(pred, target), metrics.ssim(pred, target)


def _fusion_rows(model: D2F, item: dict, use_gt: bool, theta: float) -> list[list]:
    image = item["image"].permute(1, 2, 0).numpy()
    target = item["target"].permute(1, 2, 0).numpy()
    focus, blur = _focus_blur(item, model.config)
    disparity = item["disparity"][0].numpy() if use_gt else None
    scene = model.prepare(image, disparity=disparity)
    plain = model.render(scene, focus, blur, fusion=False)
    bokeh_up = plain.bokeh
    ratio = 0.5 * (
        scene.image_lr.shape[-2] / scene.size[0] + scene.image_lr.shape[-1] / scene.size[1]
    )
    with torch.no_grad():
        d = scene.disparity_full_tensor()
        defocus = coc_to_defocus(blur * ratio * (d - focus).abs())[0, 0].cpu().numpy()
    mask = (defocus < theta).astype(np.float32)
    rows = []
    for method in FUSION_METHODS:
        t0 = time.perf_counter()
        if method == "upsample":
            pred = bokeh_up
        elif method == "alpha":
            pred = alpha_blend(image, bokeh_up, mask)
        elif method == "poisson":
            pred = poisson_blend(image, bokeh_up, mask)
        elif method == "laplacian":
            pred = laplacian_pyramid_blend(image, bokeh_up, mask)
        else:
            pred = model.render(scene, focus, blur, fusion=True).bokeh
        ms = (time.perf_counter() - t0) * 1000
        rows.append([item["id"], method, *_score(pred, target), ms])
    return rows


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="d2f-eval", description="Evaluate D2F on EBB!-format data.")
    p.add_argument("data", type=Path, help="EBB!-format data folder")
    p.add_argument("--weights", type=Path, default=None, help="D2F checkpoint")
    p.add_argument("--out", type=Path, required=True, help="output folder for the CSV")
    p.add_argument("--split", default="val470", help="train, val470, val294 or all")
    p.add_argument("--fusion", action="store_true", help="compare fusion methods")
    p.add_argument("--use-gt-disparity", action="store_true", help="use disparity/<id>.png")
    p.add_argument(
        "--baseline",
        choices=("identity", "gaussian", "gaussian-bg"),
        default=None,
        help="identity: the input; gaussian: blur everything; gaussian-bg: blur all but the "
        "in-focus pixels of the true disparity",
    )
    p.add_argument(
        "--focus-by",
        choices=("given", "click", "subject", "subject-range"),
        default="given",
        help="given: render at the pair's focal disparity; click: at the model's own disparity "
        "where the pair is in focus (the median over the pixels whose true disparity is within "
        "0.02 of the focus), as a user clicking the sharp subject would; subject: where the app "
        "and the CLI focus with no focus given (D2F.subject_focus), for pairs focused on their "
        "subject; subject-range: the same with the focal range that keeps the whole subject "
        "sharp, as a click gets it",
    )
    p.add_argument("--sigma", type=float, default=3.0, help="gaussian baseline sigma (px)")
    p.add_argument("--theta", type=float, default=0.25, help="binary-mask threshold on D")
    p.add_argument("--limit", type=int, default=None, help="evaluate the first N pairs")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def _run(args: argparse.Namespace) -> int:
    dataset = EBBDataset(args.data, split=args.split)
    count = len(dataset) if args.limit is None else min(args.limit, len(dataset))
    model = None
    if args.baseline is None:
        if args.weights is None:
            raise ValueError("--weights is required unless --baseline is given")
        model = D2F.from_checkpoint(args.weights).to(args.device)
    if args.fusion and model is None:
        raise ValueError("--fusion needs --weights (it compares fusions of the model's render)")
    if args.focus_by != "given" and (args.fusion or args.baseline is not None):
        what = "--fusion" if args.fusion else "--baseline"
        raise ValueError(f"--focus-by {args.focus_by} renders the model alone, not with {what}")
    args.out.mkdir(parents=True, exist_ok=True)
    header = (
        ["id", "method", "psnr", "ssim", "ms"]
        if args.fusion
        else ["id", "psnr", "ssim", "ms", "disp_spearman", "disp_si_rmse"]
    )
    rows: list[list] = []
    for i in range(count):
        item = dataset[i]
        if args.use_gt_disparity and not item["has_disparity"]:
            raise ValueError(f"--use-gt-disparity: pair {item['id']} has no disparity file")
        if args.fusion:
            rows += _fusion_rows(model, item, args.use_gt_disparity, args.theta)
            continue
        image = item["image"].permute(1, 2, 0).numpy()
        target = item["target"].permute(1, 2, 0).numpy()
        t0 = time.perf_counter()
        disp_err = (math.nan, math.nan)
        if args.baseline == "identity":
            pred = image
        elif args.baseline == "gaussian":
            pred = gaussian_baseline(image, args.sigma)
        elif args.baseline == "gaussian-bg":
            if not item["has_disparity"]:
                raise ValueError(f"--baseline gaussian-bg: pair {item['id']} has no disparity")
            focus, blur = _focus_blur(item, D2FConfig())
            pred = gaussian_background_baseline(image, item["disparity"][0].numpy(), focus, blur)
        else:
            focus, blur = _focus_blur(item, model.config)
            disparity = item["disparity"][0].numpy() if args.use_gt_disparity else None
            scene = model.prepare(image, disparity=disparity)
            focal_range = 0.0
            if args.focus_by == "click" and item["has_disparity"]:
                focus = click_focus(scene.disparity_full(), item["disparity"][0].numpy(), focus)
            elif args.focus_by == "subject":
                focus, _ = model.subject_focus(scene)
            elif args.focus_by == "subject-range":
                focus, _, focal_range = model.subject_focus(scene, with_range=True)
            result = model.render(scene, focus, blur, focal_range=focal_range)
            pred = result.bokeh
            if item["has_disparity"] and not args.use_gt_disparity:
                gt = torch.from_numpy(item["disparity"][0].numpy())[None, None]
                gt_lr = F.interpolate(gt, size=result.disparity.shape, mode="area")[0, 0]
                disp_err = disparity_errors(result.disparity, gt_lr.numpy())
        ms = (time.perf_counter() - t0) * 1000
        rows.append([item["id"], *_score(pred, target), ms, *disp_err])
        logger.debug("%s: PSNR %.3f SSIM %.4f %.0f ms", *rows[-1])
    name = "fusion" if args.fusion else "eval"
    path = args.out / f"{name}_{args.split}.csv"
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for row in rows:
            writer.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in row])
    what = args.baseline or str(args.weights)
    if args.fusion:
        for method in FUSION_METHODS:
            sel = [r for r in rows if r[1] == method]
            p, s, ms = (float(np.mean([r[k] for r in sel])) for k in (2, 3, 4))
            print(f"{method:10s} PSNR {p:.4f} dB  SSIM {s:.4f}  {ms:.1f} ms  ({len(sel)} images)")
    else:
        p, s, ms = (float(np.mean([r[k] for r in rows])) for k in (1, 2, 3))
        print(
            f"{what} on {args.split}: PSNR {p:.4f} dB  SSIM {s:.4f}  {ms:.1f} ms  ({count} images)"
        )
        if not math.isnan(rows[0][4]):
            rho, rmse = (float(np.mean([r[k] for r in rows])) for k in (4, 5))
            print(f"predicted disparity: Spearman {rho:.4f}  scale/shift-invariant RMSE {rmse:.4f}")
    print(f"wrote {path}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return _run(args)
    except (ValueError, FileNotFoundError) as exc:
        logger.error("%s", exc)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
