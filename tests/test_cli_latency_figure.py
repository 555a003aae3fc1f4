from __future__ import annotations

import math

import pytest
from PIL import Image

from evlatcorr.cli.latency_figure import latency_figure, write_figure_or_warn, write_latency_figure


def _rows(n: int = 6, **extra) -> list[dict]:
    """CSV-like rows (strings, as the commands write them) of ``n`` frames 25 ms apart, 20 ms exposures."""
    rows = []
    for i in range(n):
        row = {"frame": str(i), "exposure_start_us": f"{1e15 + 25000.0 * i:.1f}",
               "exposure_end_us": f"{1e15 + 25000.0 * i + 20000.0:.1f}", "latency_us": f"{3000.0 + 100 * i:.1f}",
               "latency_min_us": f"{3000.0 + 100 * i:.1f}", "latency_max_us": f"{3000.0 + 100 * i:.1f}",
               "spread_us": "500", "source": "reader", "skipped": "", "events_in_window": str(1000 * (i + 1))}
        row.update({key: value[i] for key, value in extra.items()})
        rows.append(row)
    return rows


def _line(ax, label: str):
    return next(line for line in ax.get_lines() if line.get_label().startswith(label))


def test_the_written_latency_is_drawn_in_ms_against_the_exposures_middle_in_s():
    fig = latency_figure(_rows(), "rec.aedat4")
    top, bottom = fig.axes
    written = _line(top, "written")
    assert written.get_label() == "written"  # no fused rows: no "each frame alone"
    assert list(written.get_xdata()) == pytest.approx([0.025 * i for i in range(6)], abs=1e-9)
    assert list(written.get_ydata()) == pytest.approx([3.0 + 0.1 * i for i in range(6)])
    assert top.get_title() == "rec.aedat4: 6 frames, median latency 3.30 ms"
    assert list(bottom.get_lines()[0].get_ydata()) == pytest.approx([1000.0 * (i + 1) for i in range(6)])
    assert [t.get_text() for t in top.get_legend().get_texts()] == ["± the reader's spread", "written"]
    assert bottom.get_yscale() == "log"


def test_fused_rows_show_each_frames_own_estimate_and_marked_sources():
    own = ["2000.0", "2500.0", "", "3500.0", "0.0", "4000.0"]
    rows = _rows(frame_latency_us=own, source=["reader", "reader", "", "reader", "fallback", "clipped"],
                 skipped=["", "", "no events", "", "", ""], events_in_window=["10", "20", "0", "30", "40", "50"])
    top, bottom = latency_figure(rows).axes
    alone = _line(top, "each frame alone")
    assert [v if math.isfinite(v) else None for v in alone.get_ydata()] == [2.0, 2.5, None, 3.5, 0.0, 4.0]
    assert _line(top, "written (fused").get_ydata()[2] == pytest.approx(3.2)
    for label, frames in (("fallback (no clear minimum): 1", [4]), ("black or saturated frame: 1", [5]),
                          ("no events: the previous latency: 1", [2])):
        marked = _line(top, label)
        assert list(marked.get_xdata()) == pytest.approx([0.025 * i for i in frames])
    assert bottom.get_yscale() == "symlog"  # a frame without events sits at 0


def test_each_pairs_agreement_is_drawn_where_there_is_one():
    rows = _rows(frame_latency_us=["2000.0"] * 6, pair_latency_us=["1000.0", "3000.0", "", "3200.0", "2800.0", ""])
    top, _ = latency_figure(rows).axes
    pairs = _line(top, "agreement with the next frame")
    assert list(pairs.get_xdata()) == pytest.approx([0.0, 0.025, 0.075, 0.1])
    assert list(pairs.get_ydata()) == pytest.approx([1.0, 3.0, 3.2, 2.8])


def test_a_flat_frame_is_marked():
    rows = _rows(source=["reader", "flat", "reader", "reader", "reader", "reader"])
    top, _ = latency_figure(rows).axes
    assert list(_line(top, "flat frame (no structure above noise): 1").get_xdata()) == pytest.approx([0.025])


def test_a_maps_range_is_a_band_and_rows_without_a_latency_are_left_out():
    rows = _rows(latency_min_us=["2500"] * 6, latency_max_us=["4500"] * 6)
    rows[0]["latency_us"] = ""  # e.g. deblur's last frame of an interpolation ("no next frame")
    top, _ = latency_figure(rows).axes
    assert len(_line(top, "written").get_xdata()) == 5
    assert "the map's range" in [t.get_text() for t in top.get_legend().get_texts()]
    with pytest.raises(ValueError, match="no frame has a latency"):
        latency_figure([{**row, "latency_us": ""} for row in rows])


def test_written_whole_or_not_at_all(tmp_path):
    path = write_latency_figure(_rows(), tmp_path / "sub" / "l.png")
    assert Image.open(path).format == "PNG" and not list(path.parent.glob(".*.tmp"))
    assert write_figure_or_warn([{**row, "latency_us": ""} for row in _rows()], tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()  # nothing to draw: no figure and no warning
    (tmp_path / "folder.png").mkdir()
    with pytest.warns(UserWarning, match="the latency figure .*folder.png was not written"):
        assert write_figure_or_warn(_rows(), tmp_path / "folder.png") is None
