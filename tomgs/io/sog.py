"""PlayCanvas's SOG (version 2): a static cloud for SuperSplat, the PlayCanvas engine and viewers that
read `.sog`. `sog_bytes(gaussians)` makes the bytes of one from a `tomgs.io.splats.StaticGaussians`
(what `tomgs export --frame K -o f.sog` writes).

A `.sog` is a ZIP (stored, no compression: the images are compressed already) of `meta.json` and
lossless WebP images, all of one W x H grid, Gaussian k at pixel k (row k // W), in Morton order of
the positions, as PlayCanvas's format page (developer.playcanvas.com, "The SOG Format") specifies:

    means_l.webp, means_u.webp   low and high bytes (R G B = x y z) of 16-bit positions after
                                 sign(x) log(1 + |x|), between meta.means.mins and maxs
    quats.webp                   smallest three (R G B, 255 (c sqrt 2 + 1) / 2) and A = 252 + the
                                 index of the largest component in w x y z order, made positive
    scales.webp                  R G B: indices into meta.scales.codebook (256 log scales)
    sh0.webp                     R G B: indices into meta.sh0.codebook (256 DC coefficients);
                                 A: 255 sigmoid(opacity)
    shN_centroids.webp           (SH degree d > 0) a palette of meta.shN.count entries, 64 a row,
    shN_labels.webp              each (d + 1)^2 - 1 pixels wide (R G B = the channels' coefficient
                                 j, indices into meta.shN.codebook); labels 16-bit (R low, G high)

Positions are the cloud's own axes (splat-transform keeps a PLY's axes in a SOG and back): a SOG
and the INRIA PLY of the same moment line up in any tool that reads both.
"""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np

from tomgs.io import quantise

SOG_VERSION = 2
PALETTE_ROW = 64  # SH palette entries per row of shN_centroids.webp, fixed by the format
PALETTE_SIZE = 4096  # most SH palette entries (the format allows 65536; k-means on the CPU stays seconds at 1M)


def sog_bytes(g) -> bytes:
    """The bytes of a SOG version 2 file (a ZIP) of `g`, a StaticGaussians (means [N,3], quats [N,4]
    w x y z, log_scales [N,3], opacity_logits [N], sh_dc [N,3], sh_rest [N,K-1,3])."""
    from tomgs import __version__

    n = len(g)
    width, height = quantise.grid_shape(n)
    log_means = quantise.signed_log(g.means)
    mins, maxs = (log_means.min(0), log_means.max(0)) if n else (np.zeros(3), np.zeros(3))
    q = quantise.fixed(log_means, mins, maxs, 16)
    order = quantise.morton_order(q)

    def image(values: np.ndarray, alpha: np.ndarray | None = None) -> bytes:
        """A W x H image of uint8 `values` [N, C] in Morton order (C <= 3 padded to RGB; A = `alpha`,
        or 255 when given none and C < 4), unused pixels repeating the last (all zero when N = 0)."""
        rgba = np.zeros((n, 4), np.uint8)
        rgba[:, 3] = 255
        rgba[:, :values.shape[1]] = values
        if alpha is not None:
            rgba[:, 3] = alpha
        return quantise.encode_webp(quantise.grid_image(rgba[order], width, height))

    opacity = 0.5 + 0.5 * np.tanh(0.5 * np.asarray(g.opacity_logits, np.float64))  # sigmoid, no overflow
    scales = quantise.codebook(g.log_scales)
    colours = quantise.codebook(g.sh_dc)
    files = {
        "means_l.webp": image((q & 0xFF).astype(np.uint8)),
        "means_u.webp": image((q >> 8).astype(np.uint8)),
        "quats.webp": image(quantise.smallest_three(g.quats)),
        "scales.webp": image(quantise.encode_codebook(g.log_scales, scales)),
        "sh0.webp": image(quantise.encode_codebook(g.sh_dc, colours),
                          np.clip(np.rint(opacity * 255.0), 0, 255).astype(np.uint8)),
    }
    meta = {"version": SOG_VERSION, "asset": {"generator": f"tomgs {__version__}"}, "count": n,
            "means": {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": ["means_l.webp", "means_u.webp"]},
            "scales": {"codebook": scales.tolist(), "files": ["scales.webp"]},
            "quats": {"files": ["quats.webp"]},
            "sh0": {"codebook": colours.tolist(), "files": ["sh0.webp"]}}
    degree = g.sh_degree
    if degree > 0 and n:
        coefficients = (degree + 1) ** 2 - 1
        rest = np.asarray(g.sh_rest, np.float64).reshape(n, coefficients * 3)
        centroids, labels = quantise.palette(rest, PALETTE_SIZE)
        book = quantise.codebook(centroids)
        count = len(centroids)
        rows = -(-count // PALETTE_ROW)
        cells = np.zeros((rows * PALETTE_ROW, coefficients, 4), np.uint8)
        cells[:, :, 3] = 255
        cells[:count, :, :3] = quantise.encode_codebook(centroids, book).reshape(count, coefficients, 3)
        files["shN_centroids.webp"] = quantise.encode_webp(cells.reshape(rows, PALETTE_ROW * coefficients, 4))
        files["shN_labels.webp"] = image(np.stack([labels & 0xFF, labels >> 8], axis=1).astype(np.uint8))
        meta["shN"] = {"count": count, "bands": degree, "codebook": book.tolist(),
                       "files": ["shN_centroids.webp", "shN_labels.webp"]}
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as archive:
        archive.writestr("meta.json", json.dumps(meta, separators=(",", ":")))
        for name, data in files.items():
            archive.writestr(name, data)
    return out.getvalue()
