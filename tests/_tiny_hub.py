"""Tiny, randomly initialised Hugging Face depth models saved as local model folders, for
the ``transformers:<folder>`` depth source in tests (no network: built from small configs
and written with ``save_pretrained``)."""

from __future__ import annotations

import numpy as np
import torch


def scale_weights(model: torch.nn.Module, seed: int) -> None:
    """Random weights large enough that a tiny model's output varies across the image
    (at the library's initialisation scale the ReLU head gives ~0 everywhere)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.ndim > 1:
                p.copy_(torch.randn(p.shape, generator=gen) / np.sqrt(p[0].numel()))
            elif "bias" in name:
                p.copy_(0.1 * torch.randn(p.shape, generator=gen).abs())


def save_depth_anything(folder, *, metric: bool = False) -> None:
    from transformers import (
        DepthAnythingConfig,
        DepthAnythingForDepthEstimation,
        Dinov2Config,
        DPTImageProcessor,
    )

    backbone = Dinov2Config(
        hidden_size=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=14,
        image_size=56,
        out_features=["stage1", "stage2"],
        reshape_hidden_states=False,
    )
    extra = {"depth_estimation_type": "metric", "max_depth": 20} if metric else {}
    config = DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16],
        reassemble_factors=[4, 2],
        fusion_hidden_size=16,
        head_hidden_size=8,
        patch_size=14,
        **extra,
    )
    torch.manual_seed(0)
    model = DepthAnythingForDepthEstimation(config).eval()
    scale_weights(model, 1)
    model.save_pretrained(folder)
    DPTImageProcessor(
        size={"height": 56, "width": 56}, keep_aspect_ratio=True, ensure_multiple_of=14
    ).save_pretrained(folder)


def save_dpt(folder) -> None:
    from transformers import DPTConfig, DPTForDepthEstimation, DPTImageProcessor

    config = DPTConfig(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        image_size=32,
        patch_size=8,
        backbone_out_indices=[0, 1, 2, 3],
        neck_hidden_sizes=[8, 8, 16, 16],
        fusion_hidden_size=16,
    )
    torch.manual_seed(0)
    model = DPTForDepthEstimation(config).eval()
    scale_weights(model, 2)
    model.save_pretrained(folder)
    DPTImageProcessor(size={"height": 32, "width": 32}, keep_aspect_ratio=False).save_pretrained(
        folder
    )
