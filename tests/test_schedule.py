"""The CoC <-> normalised defocus map (d2f_core.rendering.schedule) and pass-size helpers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from d2f_core.rendering.kernels import PAPER_GROWING_SIZES
from d2f_core.rendering.schedule import coc_to_defocus, defocus_to_coc
from d2f_core.sizing import resize, scaled_size, size_ratio


def test_known_points_of_the_paper_schedule():
    # the 15 kernel sizes sit at D = 0, 1/14, ..., 1
    for i, size in enumerate(PAPER_GROWING_SIZES):
        assert coc_to_defocus(float(size)) == pytest.approx(i / 14)
        assert defocus_to_coc(i / 14) == pytest.approx(size)
    assert coc_to_defocus(23.0) == pytest.approx(0.5)
    assert coc_to_defocus(0.0) == 0.0 and coc_to_defocus(500.0) == 1.0
    # halfway between 11 px (D = 4/14) and 15 px (D = 5/14)
    assert coc_to_defocus(13.0) == pytest.approx(4.5 / 14)
    assert defocus_to_coc(-1.0) == 1.0 and defocus_to_coc(2.0) == 69.0


def test_tensor_array_and_number_agree():
    coc = np.linspace(0, 120, 4801)
    as_array = coc_to_defocus(coc)
    as_tensor = coc_to_defocus(torch.from_numpy(coc).float())
    assert as_array.dtype == np.float32 and as_tensor.dtype == torch.float32
    np.testing.assert_allclose(as_tensor.numpy(), as_array, atol=1e-6)
    for c in (0.5, 2.0, 26.0, 70.0):
        assert coc_to_defocus(c) == pytest.approx(float(coc_to_defocus(torch.tensor(c))), abs=1e-6)


def test_round_trip_and_monotone():
    d = np.linspace(0, 1, 1001)
    back = np.array([coc_to_defocus(defocus_to_coc(x)) for x in d])
    np.testing.assert_allclose(back, d, atol=1e-9)
    values = coc_to_defocus(torch.linspace(0, 100, 10001))
    assert torch.all(values[1:] >= values[:-1])


def test_pass_sizes():
    assert scaled_size((1000, 1500), 0.5, None) == (500, 750)
    assert scaled_size((1000, 1500), 0.5, 600) == (400, 600)
    assert scaled_size((3, 3), 0.01, None) == (1, 1)
    assert size_ratio((500, 750), (1000, 1500)) == 0.5
    x = torch.rand(1, 3, 8, 12)
    assert resize(x, (8, 12)) is x
    assert resize(x, (4, 6)).shape == (1, 3, 4, 6)
    # a constant image stays constant, shrinking (antialiased) or growing
    c = torch.full((1, 1, 9, 7), 0.25)
    assert torch.allclose(resize(c, (3, 2)), torch.tensor(0.25))
    assert torch.allclose(resize(c, (20, 30)), torch.tensor(0.25))
