"""The D2F pipeline: networks once per image (:meth:`D2F.prepare`), then cheap refocus renders.

Inference (:meth:`D2F.render`), numbered as in the paper:

1. ``I_lr``: the photo at ``render_scale`` (0.5), long side capped at ``max_render_side``.
2. Disparity ``d`` from the defocus network at ``network_size`` (or a given map), upsampled
   to ``I_lr``'s size. Unlike the paper, which bakes the training focus into ``D = |D_d - f|``,
   the signed disparity is cached, so refocusing is a change of ``focus`` only.
3. ``R0`` from the radiance network on ``I_lr``.
4.-5. ``B_lr = rendering.render(I_lr, d, focus, K_lr, radiance=R0)`` (HDR boost inside,
   depth-ordered compositing by default).
6. Deep Poisson fusion at full resolution: ``B_up = bilinear(B_lr)``,
   ``M = max(M_s, P)``, ``B_hr = M * I_hr + (1 - M) * B_up``.

About the mask ``M``:

* ``M_s = f_p(1 - D, gray(I_hr)) * [D < fusion_gate]`` where ``D = coc_to_defocus(CoC at the
  low-res pass)``. The hard gate is part of the model (training uses it too), so running
  ``f_p`` only on the image tiles that hold pixels with ``D < fusion_gate`` is exact, and a
  12 MP fusion costs only what the in-focus part of the frame costs.
* ``P`` is an in-focus prior: 1 where the full-resolution CoC is at most ``sharp_coc`` px
  (default 1 px), falling linearly to 0 at twice that. The paper's thresholded/learned mask
  can leave no sharp region at all; with ``P`` every pixel whose CoC is below a pixel is
  guaranteed to show the sharp input, whatever ``f_p`` predicts.

Brushes (:meth:`D2F.paint`) edit the disparity of steps 4-6 for each render's focus: what is
painted sharp is drawn onto the focal plane, what is painted blurred away from it.

Checkpoints are ``{"config", "state_dict", "version"}`` files written by :meth:`D2F.save`.
"""

from __future__ import annotations

from ..depth.subject import find_subject, locate_subject
from .config import CHECKPOINT_VERSION, D2FConfig, default_weights_path
from .focus import AutoFocus
from .model import D2F
from .outputs import Result, Scene

__all__ = [
    "CHECKPOINT_VERSION",
    "AutoFocus",
    "D2F",
    "D2FConfig",
    "Result",
    "Scene",
    "default_weights_path",
    "find_subject",
    "locate_subject",
]
