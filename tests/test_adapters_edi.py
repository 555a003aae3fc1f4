from __future__ import annotations

import pytest
import torch

from evlatcorr import EventFrames
from evlatcorr.adapters.edi import EDIAdapter
from evlatcorr.edi import edi_deblur
from tests.conftest import random_events


def make_frames(with_next=False):
    ev = random_events(2000, (6, 8), (0.0, 400.0), batch_size=2, seed=3)
    kwargs = {}
    if with_next:
        kwargs = dict(blurry_next=torch.rand(2, 3, 6, 8), exposure_start_next=torch.full((2,), 200.0),
                      exposure_end_next=torch.full((2,), 300.0), target_times=torch.tensor([[150.0], [250.0]]))
    return EventFrames(torch.rand(2, 3, 6, 8), ev, torch.zeros(2), torch.full((2,), 100.0), **kwargs)


def test_deblur_matches_edi():
    frames = make_frames()
    out = EDIAdapter(num_bins=20)(frames).output
    expected = edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                          num_bins=20).clamp(0, 1)
    torch.testing.assert_close(out, expected)


def test_interpolation_blends_the_two_frames_edi():
    # mid-exposures 50 and 250 us: 150 us weighs both frames' EDI at 150 us equally, 250 us is the second's alone
    frames = make_frames(with_next=True).replace(target_times=torch.tensor([[150.0], [250.0]]))
    out = EDIAdapter("interpolation", num_bins=20)(frames).output
    assert out.shape == (2, 1, 3, 6, 8)
    time = torch.tensor([150.0, 250.0], dtype=torch.float64)
    first = edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, num_bins=20,
                       time=time)
    second = edi_deblur(frames.blurry_next, frames.events, frames.exposure_start_next, frames.exposure_end_next,
                        num_bins=20, time=time)
    torch.testing.assert_close(out[0, 0], (0.5 * first[0] + 0.5 * second[0]).clamp(0, 1))
    torch.testing.assert_close(out[1, 0], second[1].clamp(0, 1))
    torch.testing.assert_close(out[1, 0], edi_deblur(frames.blurry_next, frames.events, frames.exposure_start_next,
                                                     frames.exposure_end_next, num_bins=20)[1].clamp(0, 1))


def test_exceptions():
    with pytest.raises(ValueError, match="mode"):
        EDIAdapter("denoise")
    with pytest.raises(ValueError, match="target_times"):
        EDIAdapter("interpolation")(make_frames())

