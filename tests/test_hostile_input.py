"""Hostile and careless input through the library and the CLI: decompression bombs in the
project's own decoders, headers that claim huge sizes, files that are not regular files,
values that are out of range. Each case is refused with a ``ValueError`` that names the
problem (one line from the CLI), early, in bounded time and memory."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest
from _io_writers import png16_stream

from d2f_core.io import load_image, load_photo


def _peak(fn):
    """``(result or exception, peak bytes that Python and NumPy allocated, seconds)``."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        out = fn()
    except Exception as exc:  # returned for the caller to check
        out = exc
    seconds = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, peak, seconds


# ------------------------------------------------------------------------ 16-bit PNG


class TestPng16Bounds:
    def test_stream_that_inflates_past_the_header_is_refused(self):
        # 1x1 RGBA whose image data inflates to 64 MiB (the audit's file: 1 GiB from 1 MB)
        data = png16_stream(1, 1, 4, inflated=64 << 20)
        assert len(data) < 200_000
        out, peak, seconds = _peak(lambda: load_image(data))
        assert isinstance(out, ValueError), out
        assert "corrupt PNG image data" in str(out) and "inflates to more than" in str(out)
        assert peak < 4 << 20, f"peak {peak / 1e6:.1f} MB"
        assert seconds < 2.0

    def test_exact_stream_still_decodes(self):
        data = png16_stream(40, 30, 3)
        image = load_image(data)
        assert image.shape == (30, 40, 3)
        np.testing.assert_allclose(image[0, 0], [0x8001 / 65535, 0x4002 / 65535, 0x2003 / 65535])

    def test_size_above_the_cap_is_checked_before_decoding(self):
        # 2000x1500 16-bit RGB (36 MB as samples) under a 0.3 MP cap: read by Pillow at 8 bits
        # per channel and reduced, never decoded at full precision
        data = png16_stream(2000, 1500, 3, ftype=4)
        cap = 300_000
        out, peak, seconds = _peak(lambda: load_photo(data, max_pixels=cap))
        assert not isinstance(out, Exception), out
        h, w = out.image.shape[:2]
        assert h * w <= cap and out.info.original_size == (1500, 2000)
        assert out.info.bit_depth == 16
        assert any("16-bit PNG above max_pixels" in c for c in out.info.conversions)
        # the returned picture is 3.6 MB of float32; full precision took over 100 MB
        assert peak < 4 * h * w * 3 * 4, f"peak {peak / 1e6:.1f} MB"
        assert seconds < 5.0
