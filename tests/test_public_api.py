"""The package's public API: ``d2f_core`` names the library's entry points, lazily."""

from __future__ import annotations

import importlib
import subprocess
import sys

import numpy as np
import pytest

import d2f_core

ISSUE_23 = {"D2F", "Scene", "Result", "render_bokeh", "LayeredRenderer", "InputTypeError"}
DEPTH = {"depth_map", "DepthMap", "DepthSource", "SOURCES", "parse_source"}


def test_public_names_resolve_to_their_home_modules():
    assert ISSUE_23 | DEPTH <= set(d2f_core.__all__)
    for name in d2f_core.__all__:
        home = importlib.import_module(f"d2f_core.{d2f_core._LAZY[name]}")
        assert getattr(d2f_core, name) is getattr(home, name), name
        assert name in dir(d2f_core)
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        d2f_core.nothing  # noqa: B018


def test_docstring_names_every_public_name():
    for name in d2f_core.__all__:
        assert name in d2f_core.__doc__, name


def test_import_is_light():
    code = "import sys, d2f_core; d2f_core.__all__; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_render_bokeh_from_the_package():
    image = np.full((16, 20, 3), 0.5, np.float32)
    image[:, 10:] = 1.0
    disparity = np.zeros((16, 20), np.float32)
    sharp = d2f_core.render_bokeh(image, disparity, 0.0, 8.0)  # everything in focus
    np.testing.assert_allclose(sharp, image, atol=2e-3)
    blurred = d2f_core.render_bokeh(image, disparity, 1.0, 8.0)  # everything 8 px out
    assert blurred[:, 9].mean() > 0.55 and blurred[:, 10].mean() < 0.95
    with pytest.raises(ValueError):
        d2f_core.render_bokeh(image, disparity[:8], 0.5, 8.0)
