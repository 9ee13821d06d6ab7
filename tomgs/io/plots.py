"""PNG plots drawn with OpenCV (no matplotlib): line plots (PSNR against wall-clock seconds) and
histograms (temporal scales, optionally on a log axis). White background, axes with tick labels,
title, legend when there are several series. Files are written atomically (temporary name, rename).

OpenCV is imported inside the functions so that `import tomgs` stays cheap.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tomgs.outputs import write_bytes

WIDTH, HEIGHT = 800, 500
MARGIN_LEFT, MARGIN_RIGHT, MARGIN_TOP, MARGIN_BOTTOM = 80, 24, 44, 58
# BGR colours of successive series (matplotlib's tab10 order)
COLORS = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148),
          (75, 86, 140), (194, 119, 227), (127, 127, 127), (34, 189, 188), (207, 190, 23)]
FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX
GRID = (225, 225, 225)
INK = (40, 40, 40)


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round tick values (1, 2, 2.5, 5 x 10^k steps) covering [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(count - 1, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(s * mag for s in (1, 2, 2.5, 5, 10) if s * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = []
    v = first
    while v <= hi + step * 1e-9:
        ticks.append(round(v, 12))
        v += step
    return ticks


def _fmt(v: float, log: bool = False) -> str:
    if log:
        e = int(round(math.log10(v)))
        return f"1e{e}" if abs(e) >= 4 else f"{10.0 ** e:g}"
    if v == 0:
        return "0"
    if abs(v) >= 1e5 or abs(v) < 1e-3:
        return f"{v:.0e}"
    return f"{v:g}"


def _padded_range(lo: float, hi: float, pad: float = 0.05) -> tuple[float, float]:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return 0.0, 1.0
    if hi <= lo:
        d = abs(lo) * 0.1 or 1.0
        return lo - d, hi + d
    d = (hi - lo) * pad
    return lo - d, hi + d


class _Canvas:
    """A white image with a plot area and a linear or log10 mapping of data to pixels."""

    def __init__(self, width: int, height: int, xlim, ylim, log_x: bool = False):
        import cv2

        self.cv2 = cv2
        self.img = np.full((height, width, 3), 255, np.uint8)
        self.x0, self.x1 = MARGIN_LEFT, width - MARGIN_RIGHT
        self.y0, self.y1 = MARGIN_TOP, height - MARGIN_BOTTOM  # top, bottom of the plot area
        self.log_x = log_x
        self.xlim = (math.log10(xlim[0]), math.log10(xlim[1])) if log_x else xlim
        self.ylim = ylim

    def px(self, x) -> np.ndarray:
        x = np.asarray(x, np.float64)
        if self.log_x:
            x = np.log10(np.maximum(x, 1e-300))
        lo, hi = self.xlim
        return self.x0 + (x - lo) / (hi - lo) * (self.x1 - self.x0)

    def py(self, y) -> np.ndarray:
        lo, hi = self.ylim
        return self.y1 - (np.asarray(y, np.float64) - lo) / (hi - lo) * (self.y1 - self.y0)

    def text(self, s: str, x: float, y: float, scale: float = 0.45, anchor: str = "left", thickness: int = 1):
        (w, h), _ = self.cv2.getTextSize(s, FONT, scale, thickness)
        dx = {"left": 0, "center": -w / 2, "right": -w}[anchor]
        self.cv2.putText(self.img, s, (int(round(x + dx)), int(round(y + h / 2))), FONT, scale, INK, thickness,
                         self.cv2.LINE_AA)

    def vertical_text(self, s: str, x: float, y: float, scale: float = 0.5):
        cv2 = self.cv2
        (w, h), base = cv2.getTextSize(s, FONT, scale, 1)
        patch = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
        cv2.putText(patch, s, (2, h + 2), FONT, scale, INK, 1, cv2.LINE_AA)
        patch = cv2.rotate(patch, cv2.ROTATE_90_COUNTERCLOCKWISE)
        ph, pw = patch.shape[:2]
        top, left = int(y - ph / 2), int(x - pw / 2)
        top, left = max(top, 0), max(left, 0)
        region = self.img[top:top + ph, left:left + pw]
        np.minimum(region, patch[:region.shape[0], :region.shape[1]], out=region)

    def axes(self, xlabel: str, ylabel: str, title: str):
        cv2 = self.cv2
        if self.log_x:
            lo, hi = self.xlim
            xticks = [10.0 ** e for e in range(math.ceil(lo - 1e-9), math.floor(hi + 1e-9) + 1)]
            if len(xticks) < 2:  # less than a decade: linear ticks inside it
                xticks = [v for v in nice_ticks(10 ** lo, 10 ** hi, 5) if v > 0]
                labels = [_fmt(v) for v in xticks]
            else:
                labels = [_fmt(v, log=True) for v in xticks]
        else:
            xticks = nice_ticks(*self.xlim)
            labels = [_fmt(v) for v in xticks]
        for v, label in zip(xticks, labels):
            x = int(round(float(self.px(v))))
            if self.x0 <= x <= self.x1:
                cv2.line(self.img, (x, self.y0), (x, self.y1), GRID, 1)
                cv2.line(self.img, (x, self.y1), (x, self.y1 + 5), INK, 1)
                self.text(label, x, self.y1 + 16, anchor="center")
        for v in nice_ticks(*self.ylim):
            y = int(round(float(self.py(v))))
            if self.y0 <= y <= self.y1:
                cv2.line(self.img, (self.x0, y), (self.x1, y), GRID, 1)
                cv2.line(self.img, (self.x0 - 5, y), (self.x0, y), INK, 1)
                self.text(_fmt(v), self.x0 - 8, y, anchor="right")
        cv2.rectangle(self.img, (self.x0, self.y0), (self.x1, self.y1), INK, 1)
        self.text(xlabel, (self.x0 + self.x1) / 2, self.img.shape[0] - 16, scale=0.5, anchor="center")
        self.vertical_text(ylabel, 16, (self.y0 + self.y1) / 2)
        self.text(title, self.img.shape[1] / 2, 20, scale=0.6, anchor="center", thickness=1)

    def legend(self, names: list[str]):
        cv2 = self.cv2
        sizes = [cv2.getTextSize(n, FONT, 0.45, 1)[0] for n in names]
        w = max(s[0] for s in sizes) + 44
        row = 20
        h = row * len(names) + 8
        # the corner of the plot area that the data covers least
        corners = [(self.x1 - w - 10, self.y0 + 10), (self.x0 + 10, self.y0 + 10),
                   (self.x1 - w - 10, self.y1 - h - 10), (self.x0 + 10, self.y1 - h - 10)]
        def ink(corner):
            patch = self.img[corner[1]:corner[1] + h + 1, corner[0]:corner[0] + w + 1].astype(np.int16)
            return int((np.ptp(patch, axis=2) > 40).sum())  # coloured pixels (curves), not grey grid
        left, top = min(corners, key=ink)
        cv2.rectangle(self.img, (left, top), (left + w, top + h), (255, 255, 255), -1)
        cv2.rectangle(self.img, (left, top), (left + w, top + h), (180, 180, 180), 1)
        for i, name in enumerate(names):
            y = top + 4 + row * i + row // 2
            cv2.line(self.img, (left + 8, y), (left + 30, y), COLORS[i % len(COLORS)], 2, cv2.LINE_AA)
            self.text(name, left + 36, y)


def _write_png(path, img: np.ndarray) -> Path:
    """Encode and write atomically (temporary file in the same folder, then rename)."""
    import cv2

    path = Path(path)
    if not path.parent.exists():
        raise ValueError(f"{path}: folder {path.parent} does not exist; create it or choose another path")
    ok, data = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: could not encode the plot as PNG")
    write_bytes(path, data.tobytes())
    return path


def line_plot_png(path, series: dict, xlabel: str = "", ylabel: str = "", title: str = "",
                  width: int = WIDTH, height: int = HEIGHT) -> Path:
    """Line plot of `series` {name: (xs, ys)} to a PNG at `path` (e.g. PSNR against wall-clock seconds).

    Non-finite points are skipped; a series of one point is drawn as a dot. A legend is drawn when
    there are several series. Returns the path."""
    return _write_png(path, _line_panel(series, xlabel, ylabel, title, width, height))


def line_plots_png(path, panels: list[dict], width: int = WIDTH, height: int = HEIGHT) -> Path:
    """Line plots stacked top to bottom in one PNG at `path`, each `panels` entry the keyword arguments
    of `line_plot_png` but the path and size (series, and xlabel, ylabel, title when given), each panel
    `width` x `height`. Returns the path."""
    return _write_png(path, np.concatenate([_line_panel(width=width, height=height, **panel) for panel in panels]))


def _line_panel(series: dict, xlabel: str = "", ylabel: str = "", title: str = "", width: int = WIDTH,
                height: int = HEIGHT) -> np.ndarray:
    """`line_plot_png`'s image: uint8 [height, width, 3] BGR."""
    import cv2

    clean = {}
    for name, (xs, ys) in series.items():
        xs, ys = np.asarray(xs, np.float64).ravel(), np.asarray(ys, np.float64).ravel()
        if xs.shape != ys.shape:
            raise ValueError(f"line_plot_png: series {name!r} has {xs.size} x values but {ys.size} y values")
        keep = np.isfinite(xs) & np.isfinite(ys)
        clean[name] = (xs[keep], ys[keep])
    all_x = np.concatenate([xs for xs, _ in clean.values()] + [np.zeros(0)])
    all_y = np.concatenate([ys for _, ys in clean.values()] + [np.zeros(0)])
    xlim = (float(all_x.min()), float(all_x.max())) if all_x.size else (0.0, 1.0)
    if xlim[1] <= xlim[0]:
        xlim = _padded_range(*xlim)
    ylim = _padded_range(float(all_y.min()), float(all_y.max())) if all_y.size else (0.0, 1.0)
    canvas = _Canvas(width, height, xlim, ylim)
    canvas.axes(xlabel, ylabel, title)
    for i, (xs, ys) in enumerate(clean.values()):
        color = COLORS[i % len(COLORS)]
        if xs.size == 0:
            continue
        pts = np.stack([canvas.px(xs), canvas.py(ys)], 1)
        pts = np.round(pts * 16).astype(np.int32)  # 4 fractional bits: smooth curves
        if xs.size == 1:
            cv2.circle(canvas.img, tuple(int(v) for v in pts[0]), 4 * 16, color, -1, cv2.LINE_AA, shift=4)
        else:
            cv2.polylines(canvas.img, [pts.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA, shift=4)
    if len(clean) > 1:
        canvas.legend(list(clean))
    return canvas.img


def histogram_png(path, values, bins: int = 40, log_x: bool = False, xlabel: str = "", title: str = "",
                  ylabel: str = "count", width: int = WIDTH, height: int = HEIGHT) -> Path:
    """Histogram of `values` to a PNG at `path`; `log_x` bins and draws the x axis in log10 (values
    <= 0 and non-finite values are dropped, and the title says how many). Returns the path."""
    import cv2

    v = np.asarray(values, np.float64).ravel()
    keep = np.isfinite(v) & ((v > 0) if log_x else True)
    dropped = int(v.size - keep.sum())
    v = v[keep]
    if dropped:
        title = f"{title} ({dropped} {'non-positive or ' if log_x else ''}non-finite values left out)"
    if v.size:
        lo, hi = float(v.min()), float(v.max())
    else:
        lo, hi = (1.0, 10.0) if log_x else (0.0, 1.0)
    if log_x:
        llo, lhi = math.log10(lo), math.log10(hi)
        if lhi <= llo:
            llo, lhi = llo - 0.5, lhi + 0.5
        edges = np.logspace(llo, lhi, bins + 1)
    else:
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.linspace(lo, hi, bins + 1)
    counts, _ = np.histogram(v, bins=edges)
    ylim = (0.0, max(float(counts.max()) * 1.08, 1.0))
    canvas = _Canvas(width, height, (float(edges[0]), float(edges[-1])), ylim, log_x=log_x)
    canvas.axes(xlabel, ylabel, title)
    xs = canvas.px(edges)
    base = canvas.y1
    for i, c in enumerate(counts):
        if c == 0:
            continue
        top = int(round(float(canvas.py(c))))
        left, right = int(round(xs[i])), max(int(round(xs[i + 1])) - 1, int(round(xs[i])))
        cv2.rectangle(canvas.img, (left, top), (right, base), COLORS[0], -1)
        cv2.rectangle(canvas.img, (left, top), (right, base), (120, 70, 20), 1)
    cv2.rectangle(canvas.img, (canvas.x0, canvas.y0), (canvas.x1, canvas.y1), INK, 1)
    return _write_png(path, canvas.img)


__all__ = ["line_plot_png", "line_plots_png", "histogram_png", "nice_ticks"]
