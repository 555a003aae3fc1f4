from __future__ import annotations

import math

import kornia
import pytest
import torch

from evlatcorr import etf


def step_image(size=16, dtype=torch.float32):
    img = torch.zeros(1, 1, size, size, dtype=dtype)
    img[..., size // 2:] = 1.0
    return img


class TestEdgeThickness:
    def test_smoke_shapes(self):
        assert etf.edge_thickness(torch.rand(3, 3, 8, 9)).shape == (3,)

    def test_known_answer_step(self):
        # central differences (normalised: /2) of a unit step: |∇I| = 0.5 on the two columns beside the
        # edge, 0 elsewhere (replicate border) -> mean = 2/16 (1 - e^{-0.5 ε})
        eps = 4.0
        expected = 2 / 16 * (1 - math.exp(-0.5 * eps))
        assert etf.edge_thickness(step_image(), eps).item() == pytest.approx(expected, rel=1e-4)

    def test_blur_thickens(self):
        sharp = step_image()
        blurred = kornia.filters.box_blur(sharp, (1, 7))
        assert etf.edge_thickness(blurred).item() > etf.edge_thickness(sharp).item()

    def test_exceptions(self):
        with pytest.raises(ValueError, match="epsilon"):
            etf.edge_thickness(step_image(), 0.0)
        with pytest.raises(ValueError, match="shape"):
            etf.edge_thickness(torch.rand(8, 8))
        with pytest.raises(ValueError, match="channels"):
            etf.edge_thickness(torch.rand(1, 2, 8, 8))

    def test_gradcheck(self):
        img = torch.rand(1, 1, 5, 5, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: etf.edge_thickness(x, 3.0), (img,))

    def test_module(self):
        img = torch.rand(2, 1, 8, 8)
        torch.testing.assert_close(etf.EdgeThickness(5.0)(img), etf.edge_thickness(img, 5.0))
        assert "epsilon=5.0" in repr(etf.EdgeThickness(5.0))


class TestLocalContrast:
    def test_constant_image_has_no_contrast(self):
        assert etf.local_contrast(torch.full((1, 1, 9, 9), 0.4)).item() == pytest.approx(0.0, abs=1e-3)

    def test_known_answer_checkerboard(self):
        # columns alternating 0/1: any 3x3 window holds 3 or 6 ones of 9 -> std = sqrt(p(1-p)) = sqrt(2)/3
        img = torch.zeros(1, 1, 9, 9, dtype=torch.float64)
        img[..., ::2] = 1.0
        assert etf.local_contrast(img, 3).item() == pytest.approx(math.sqrt(2) / 3, abs=1e-4)

    def test_exceptions(self):
        with pytest.raises(ValueError, match="window"):
            etf.local_contrast(torch.rand(1, 1, 8, 8), 4)

    @pytest.mark.parametrize("size", [(3, 16), (16, 3), (1, 1)])
    def test_image_smaller_than_the_reflected_box_is_refused(self, size):
        # a 7x7 box reflects 3 pixels at each border: an image 3 pixels high has no 4th row to reflect
        with pytest.raises(ValueError, match="at least 4 pixels on each side"):
            etf.local_contrast(torch.rand(1, 1, *size))
        with pytest.raises(ValueError, match="smaller window"):
            etf.EventTemporalFidelity()(torch.rand(2, 3, *size))
        assert torch.isfinite(etf.local_contrast(torch.rand(1, 1, *size), window=1)).all()

    def test_smallest_image_the_box_takes(self):
        assert torch.isfinite(etf.local_contrast(torch.rand(1, 1, 4, 4))).all()

    def test_module_and_non_contiguous(self):
        img = torch.rand(1, 1, 9, 8).transpose(-1, -2)
        torch.testing.assert_close(etf.LocalContrast(5)(img), etf.local_contrast(img.contiguous(), 5))


class TestTemporalConsistency:
    def test_values(self):
        lat = torch.tensor([1000.0, 2000.0])
        g = etf.temporal_consistency(lat, torch.tensor([1000.0, 1000.0]), sigma_us=1000.0)
        torch.testing.assert_close(g, torch.tensor([1.0, math.exp(-0.5)]) / (2 * math.pi))
        torch.testing.assert_close(etf.temporal_consistency(lat, None), torch.full((2,), 1 / (2 * math.pi)))

    def test_candidates_broadcast(self):
        g = etf.temporal_consistency(torch.zeros(2, 5), torch.tensor([0.0, 1.0]))
        assert g.shape == (2, 5)

    def test_exceptions(self):
        with pytest.raises(ValueError, match="sigma"):
            etf.temporal_consistency(torch.zeros(1), None, 0.0)


class TestETF:
    def test_sharp_beats_blurred(self):
        sharp = step_image()
        for k in (3, 5, 9):
            assert etf.etf_loss(sharp).item() < etf.etf_loss(kornia.filters.box_blur(sharp, (1, k))).item()

    def test_formula(self):
        img = torch.rand(2, 3, 12, 12)
        lat, prev = torch.tensor([100.0, 3000.0]), torch.tensor([0.0, 0.0])
        contrast = etf.local_contrast(img) * etf.temporal_consistency(lat, prev)
        expected = etf.edge_thickness(img) / torch.sqrt(contrast + 1e-8)
        torch.testing.assert_close(etf.etf_loss(img, lat, prev), expected)

    def test_temporal_term_penalises_jumps(self):
        img = torch.rand(1, 1, 12, 12)
        near = etf.etf_loss(img, torch.tensor([1000.0]), torch.tensor([1000.0]))
        far = etf.etf_loss(img, torch.tensor([4000.0]), torch.tensor([1000.0]))
        assert far.item() > near.item()

    def test_gradcheck(self):
        img = (torch.rand(1, 1, 6, 6, dtype=torch.float64) + 0.1).requires_grad_()
        assert torch.autograd.gradcheck(lambda x: etf.etf_loss(x, epsilon=3.0, window=3), (img,))

    def test_module(self, device):
        img = torch.rand(2, 1, 10, 10, device=device)
        module = etf.EventTemporalFidelity(epsilon=10.0, window=5)
        torch.testing.assert_close(module(img), etf.etf_loss(img, epsilon=10.0, window=5))
        assert "window=5" in repr(module)
