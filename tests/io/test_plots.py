"""PNG plots drawn with OpenCV: right size, curve pixels where the data is, legends, log axes, atomic writes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tomgs.io.plots import COLORS, MARGIN_BOTTOM, MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, histogram_png, \
    line_plot_png, nice_ticks


def _read(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, f"{path} is not a readable PNG"
    return img


def _colour_mask(img, bgr, tol=40):
    return (np.abs(img.astype(int) - np.array(bgr)).max(axis=2) < tol)


def test_line_plot_size_and_curve_position(tmp_path):
    path = tmp_path / "psnr.png"
    xs = np.linspace(0.0, 100.0, 50)
    ys = 20.0 + 0.1 * xs  # a rising line: left end low, right end high
    assert line_plot_png(path, {"train": (xs, ys)}, "wall-clock seconds", "PSNR (dB)", "PSNR") == path
    img = _read(path)
    assert img.shape == (500, 800, 3)
    assert (img[0, 0] == 255).all() and (img[-1, -1] == 255).all()  # white background
    blue = _colour_mask(img, COLORS[0])
    assert blue.sum() > 500  # the curve is drawn
    rows, cols = np.nonzero(blue)
    plot_w = 800 - MARGIN_LEFT - MARGIN_RIGHT
    left, right = cols < MARGIN_LEFT + plot_w * 0.2, cols > MARGIN_LEFT + plot_w * 0.8
    assert rows[left].mean() > rows[right].mean() + 100  # rising: lower on the left (larger row index)
    assert MARGIN_TOP - 3 <= rows.min() and rows.max() <= 500 - MARGIN_BOTTOM + 3  # inside the plot area
    # something dark (axes, tick labels, title) outside the plot area
    assert (img[: MARGIN_TOP - 5] < 100).any() and (img[:, : MARGIN_LEFT - 10] < 100).any()
    assert not list(tmp_path.glob(".*"))  # no temporary left behind


def test_line_plot_several_series_have_a_legend_and_own_colours(tmp_path):
    path = tmp_path / "two.png"
    xs = np.arange(10.0)
    line_plot_png(path, {"a": (xs, xs), "b": (xs, 10 - xs), "single": ([5.0], [5.0])}, "x", "y", "three")
    img = _read(path)
    for colour in COLORS[:3]:
        assert _colour_mask(img, colour).sum() > 20


def test_line_plot_rejects_mismatched_series_and_missing_folder(tmp_path):
    with pytest.raises(ValueError, match="x values"):
        line_plot_png(tmp_path / "x.png", {"a": ([1, 2, 3], [1, 2])})
    with pytest.raises(ValueError, match="does not exist"):
        line_plot_png(tmp_path / "missing" / "x.png", {"a": ([1, 2], [1, 2])})


def test_line_plot_survives_degenerate_data(tmp_path):
    line_plot_png(tmp_path / "flat.png", {"a": ([0, 1, 2], [3, 3, 3])})
    line_plot_png(tmp_path / "nan.png", {"a": ([0, 1, 2], [np.nan, np.inf, 1.0])})
    line_plot_png(tmp_path / "empty.png", {"a": ([], [])})
    for name in ("flat", "nan", "empty"):
        assert _read(tmp_path / f"{name}.png").shape == (500, 800, 3)


def test_histogram_linear_and_log(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "hist.png"
    values = np.concatenate([np.full(1000, 1e-3), np.full(10, 1.0)])  # tall bar left, short bar right
    histogram_png(path, values, bins=30, log_x=True, xlabel="temporal scale", title="scales")
    img = _read(path)
    assert img.shape == (500, 800, 3)
    bars = _colour_mask(img, COLORS[0])
    cols = np.nonzero(bars)[1]
    plot_w = 800 - MARGIN_LEFT - MARGIN_RIGHT
    assert (cols < MARGIN_LEFT + plot_w * 0.1).sum() > 5 * (cols > MARGIN_LEFT + plot_w * 0.9).sum() > 0
    tall = bars[:, cols.min():cols.min() + 5].any(axis=1).sum()
    short = bars[:, cols.max() - 5:cols.max() + 1].any(axis=1).sum()
    assert tall > 20 * short > 0
    histogram_png(tmp_path / "lin.png", rng.normal(size=2000), bins=40, xlabel="x", title="normal")
    assert _colour_mask(_read(tmp_path / "lin.png"), COLORS[0]).sum() > 5000
    histogram_png(tmp_path / "neg.png", [-1.0, 0.0, 1.0, 2.0], log_x=True)  # non-positive left out
    histogram_png(tmp_path / "one.png", [5.0] * 3)
    histogram_png(tmp_path / "none.png", [])


def test_nice_ticks():
    assert nice_ticks(0, 100) == [0, 20, 40, 60, 80, 100]
    ticks = nice_ticks(19.3, 31.7)
    assert ticks[0] >= 19.3 and ticks[-1] <= 31.7 and 4 <= len(ticks) <= 8
