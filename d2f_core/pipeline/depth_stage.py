"""The depth steps of D2F: the defocus network's map of a photo (paper step 2, ``d =
f_d(I_lr)``), the scene head's subjects stood on it, and the edge-aware refinement every
map gets, as methods of :class:`~d2f_core.pipeline.D2F`.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from ..depth.refine import equalize, harden_edges, snap_edges
from ..sizing import resize, scaled_size

__all__ = ["DepthStage", "check_photo"]


def check_photo(photo: Tensor, image: Tensor) -> None:
    """``photo`` (B, 3, H, W) must be ``image``'s photo: the same batch and channels, float,
    at least as large, and the same frame within a pixel of rounding.

    Raises:
        ValueError: naming what differs.
    """
    if photo.dim() != 4 or photo.shape[:2] != image.shape[:2]:
        raise ValueError(
            f"photo must be the image's batch at its own size, (B, C, H, W) = "
            f"{tuple(image.shape[:2])} + (H, W); got {tuple(photo.shape)}"
        )
    if not photo.is_floating_point():
        raise ValueError(f"photo must be float in [0, 1], got {photo.dtype}")
    (ph, pw), (h, w) = photo.shape[-2:], image.shape[-2:]
    if ph < h or pw < w:
        raise ValueError(f"photo ({ph}x{pw}) is smaller than the image ({h}x{w})")
    scale = w / pw if pw >= ph else h / ph  # the long side's scale: the one rounded least
    if abs(ph * scale - h) > 1 or abs(pw * scale - w) > 1:
        raise ValueError(f"photo ({ph}x{pw}) and image ({h}x{w}) are not the same frame")


class DepthStage:
    """The defocus network's map, its subjects and the map's refinement, as methods of
    :class:`~d2f_core.pipeline.D2F` (which holds ``config`` and ``defocus_net``)."""

    def predict_disparity(
        self, image: Tensor, refine: bool = True, photo: Tensor | None = None
    ) -> Tensor:
        """Defocus network at ``config.network_size`` (averaged with its mirror image with
        ``config.flip_average``), resized back to the input size; with ``refine`` and
        ``config.refine="snap"`` its edges are then moved onto the photo's
        (:func:`refine.snap_edges`); with ``config.spread`` the map is then partly equalised
        (:func:`refine.equalize`).

        Args:
            image: the photo at the size the map is wanted at (the rendering pass's).
            refine: snap the map's edges onto ``image``'s.
            photo: the same photo at a larger size (its own), which the network then reads,
                at up to ``network_size``, when ``image`` is smaller than that: a photo of
                400 px has a rendering pass of 200 px, and the network sees it at 400 (it
                was trained at 256-384). A pass of ``network_size`` or more is read as it is.

        Shape: (B, 3, h, w) in [0, 1] -> (B, 1, h, w) in [0, 1].
        """
        return self.disparity_and_scene_maps(image, refine, photo)[0]

    def disparity_and_scene_maps(
        self,
        image: Tensor,
        refine: bool = True,
        photo: Tensor | None = None,
        blend: float | None = None,
    ) -> tuple[Tensor, Tensor | None]:
        """:meth:`predict_disparity` and, from the same network pass, the scene head's
        probabilities (subject, sky) at the size the network read the photo (``None`` for a
        network that stands no subjects); ``blend`` in place of ``config.subject_blend``.

        Shape: (B, 3, h, w) -> (B, 1, h, w) in [0, 1] and (B, 2, hn, wn) in [0, 1].
        """
        size = tuple(image.shape[-2:])
        if photo is not None:
            check_photo(photo, image)
        # the photo only when the pass is smaller than the network reads (one resize of a
        # large photo would cost more than the network)
        small_pass = max(size) < self.config.network_size
        source = photo if photo is not None and small_pass else image
        net_size = scaled_size(tuple(source.shape[-2:]), 1.0, self.config.network_size)
        small = resize(source, net_size)
        d, maps = self._network_pass(small, self.stands_subjects)
        probs = None if maps is None else torch.sigmoid(maps)
        if probs is not None:
            d = self._stand(d, probs, blend)
        d = resize(d, size)  # [B,1,h,w]
        if refine:
            d = self._snap(image, d)
        d = d.clamp(0, 1)
        if self.config.spread > 0:
            s = self.config.spread
            d = (1 - s) * d + s * equalize(d, self.config.spread_clip)
        return d, probs

    @property
    def stands_subjects(self) -> bool:
        """Whether :meth:`predict_disparity` runs the scene head and stands its subjects: a
        ``"-scene"`` network with ``config.subject_lift`` or ``config.subject_blend`` over 0."""
        return self.defocus_net.scene_head is not None and (
            self.config.subject_lift > 0 or self.config.subject_blend > 0
        )

    def _network_pass(self, small: Tensor, scene: bool) -> tuple[Tensor, Tensor | None]:
        """The defocus network on a photo at the size it reads (averaged with its mirror
        image with ``config.flip_average``): the disparity, and with ``scene`` the scene
        head's logits (else ``None``)."""
        net = self.defocus_net
        forward = net.forward_scene if scene else lambda x: (net(x), None)
        if not self.config.flip_average:
            return forward(small)
        b = small.shape[0]
        both, maps = forward(torch.cat([small, small.flip(-1)]))  # [2B,1,hn,wn]
        d = 0.5 * (both[:b] + both[b:].flip(-1))
        if maps is not None:
            maps = 0.5 * (maps[:b] + maps[b:].flip(-1))
        return d, maps

    def _stand(self, disparity: Tensor, maps: Tensor, blend: float | None = None) -> Tensor:
        """:meth:`stand` on each map of a batch, with the scene head's probabilities
        ``maps`` (subject, sky)."""
        out = []
        for d, m in zip(disparity, maps, strict=True):
            subject, sky = m.float().cpu().numpy()[:2]
            stood = self.stand(d[0].float().cpu().numpy(), subject, sky, blend)
            out.append(torch.from_numpy(stood))
        return torch.stack(out)[:, None].to(disparity)

    def stand(
        self,
        disparity: np.ndarray,
        subject: np.ndarray,
        sky: np.ndarray,
        blend: float | None = None,
    ) -> np.ndarray:
        """:func:`~d2f_core.depth.scene.stand_subjects` with this model's settings
        (``config.subject_lift``, ``subject_clarity``, ``subject_shift``, and
        ``subject_blend`` unless ``blend`` is given):
        what :meth:`predict_disparity` does to the network's map with the scene head's
        ``subject`` and ``sky`` probabilities, for any ``H x W`` map of the same shape."""
        from ..depth.scene import stand_subjects

        shift = self.config.subject_shift if self.config.subject_shift < 1 else math.inf
        return stand_subjects(
            disparity,
            subject,
            sky,
            lift=self.config.subject_lift,
            min_clarity=self.config.subject_clarity,
            max_shift=shift,
            blend=self.config.subject_blend if blend is None else blend,
        )

    def scene_maps(self, image: Tensor) -> Tensor | None:
        """The scene head's probabilities (subject, sky) for a photo, at the size the
        network reads it (``config.network_size``, mirrored and averaged with
        ``config.flip_average``, as :meth:`predict_disparity`); ``None`` for a network
        without the head.

        Shape: (B, 3, h, w) in [0, 1] -> (B, 2, hn, wn) in [0, 1].
        """
        if self.defocus_net.scene_head is None:
            return None
        small = resize(image, scaled_size(tuple(image.shape[-2:]), 1.0, self.config.network_size))
        with torch.no_grad():
            _, maps = self._network_pass(small, scene=True)
        return torch.sigmoid(maps)

    def _snap(self, image: Tensor, disparity: Tensor) -> Tensor:
        if self.config.refine != "snap":
            return disparity
        radius = max(1, round(self.config.refine_radius * max(image.shape[-2:])))
        return snap_edges(image, disparity, radius, self.config.refine_eps).clamp_(0, 1)

    def refine_disparity(self, image: Tensor, disparity: Tensor) -> Tensor:
        """Edge-aware refinement of a disparity map from any source, guided by the photo at
        the map's size (:meth:`prepare` runs it at the rendering pass's size): with
        ``config.edge_step > 0`` every pixel on a silhouette's ramp is put on one side of it
        by its colour (:func:`refine.harden_edges`).

        The snapping of ``config.refine="snap"`` belongs to the defocus network's own map
        (:meth:`predict_disparity`), a soft map at ``network_size``; on a phone's map it
        copies the photo's texture into the depth (the portrait with a matte, at 768x1024:
        depth-edge pixels 12k -> 48k, the silhouette's IoU with the matte 0.653 -> 0.597).

        Shape: image (1, 3, h, w) in [0, 1], disparity (1, 1, h, w) -> (1, 1, h, w) in [0, 1].
        """
        if self.config.edge_step <= 0:
            return disparity
        radius = max(3, round(self.config.edge_radius * max(image.shape[-2:])))
        return harden_edges(image, disparity, radius, self.config.edge_step)
