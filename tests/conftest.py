from __future__ import annotations

from evlatcorr.pages import prefer_fast_memory

prefer_fast_memory()  # as the command lines and scripts do, before the first tensor

import pytest  # noqa: E402
import torch  # noqa: E402

from evlatcorr import Events  # noqa: E402

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    return torch.device(request.param)


def textured_frames(*shape: int, seed: int = 0) -> torch.Tensor:
    """Seeded frames ``(B, C, H, W)`` in [0.1, 0.9]: a diagonal ramp under white noise. White noise alone is flat
    to the latency search (:mod:`evlatcorr.blank_frames`), which does not search such frames."""
    *_, height, width = shape
    ramp = (torch.arange(height)[:, None] + torch.arange(width)[None, :]).float() / max(1, height + width - 2)
    return 0.1 + 0.3 * torch.rand(*shape, generator=torch.Generator().manual_seed(seed)) + 0.5 * ramp


def random_events(num: int, sensor_size: tuple[int, int], t_range: tuple[float, float], batch_size: int = 1,
                  seed: int = 0) -> Events:
    """Uniformly random events, sorted, for tests."""
    g = torch.Generator().manual_seed(seed)
    height, width = sensor_size
    x = torch.randint(0, width, (num,), generator=g)
    y = torch.randint(0, height, (num,), generator=g)
    t = torch.rand(num, generator=g, dtype=torch.float64) * (t_range[1] - t_range[0]) + t_range[0]
    p = torch.randint(0, 2, (num,), generator=g)
    b = torch.randint(0, batch_size, (num,), generator=g)
    return Events(x, y, t, p, b, sensor_size=sensor_size, batch_size=batch_size, sort=True)


def shared_data_dir():
    """The project's shared data folder: ../shared beside the checkout, else /work/shared (may be absent)."""
    import os
    from pathlib import Path

    for candidate in (os.environ.get("EVLATCORR_SHARED"), Path(__file__).resolve().parents[2] / "shared",
                      "/work/shared"):
        if candidate and (Path(candidate) / "data").is_dir():
            return Path(candidate) / "data"
    return Path("/nonexistent")
