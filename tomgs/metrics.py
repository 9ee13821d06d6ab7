"""Image quality: PSNR, SSIM and LPIPS (AlexNet, v0.1 heads) as the peers compute them, and `evaluate`.

Images are float tensors in [0, 1], shape [H,W,3] or batched [B,H,W,3], on any device; each metric
returns one value per image (a 0-d tensor for [H,W,3], [B] for a batch). Protocol (the papers'
evaluation, as their numbers were made): float renders, no 8-bit rounding; PSNR per frame, averaged over frames.
`frame_psnr` is a fit's own measure of its frames (one render each, no LPIPS or SSIM).

`l1_dssim` is the training loss, (1 - w) L1 + w (1 - SSIM), in the SSIM passes (no torch operation
over the image, forward or backward); `l1_dssim_and_psnr` also gives the PSNR, from the same sums.

SSIM follows the 3DGS implementation exactly: 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2,
C2 = 0.03^2, per channel, zero "same" padding (conv2d padding=5), mean over all pixels and
channels. It is differentiable (the training loss uses 1 - SSIM). Two implementations of one
formula: float32 images with a constant reference go through four Warp passes that also give the
gradient (tomgs/kernels/ssim.py: a training step's SSIM in one pass each way instead of a dozen
torch ops); anything else (float64, a reference that needs a gradient) through two separable
convolutions of the five moments, which the tests hold the Warp passes against.

LPIPS needs its weights as an npz file (no downloads): pass the path, or set TOMGS_LPIPS_WEIGHTS.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tomgs.errors import counted

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2
LPIPS_ENV = "TOMGS_LPIPS_WEIGHTS"


def _check_pair(img: torch.Tensor, ref: torch.Tensor, what: str) -> bool:
    """Whether the images are a batch [B,H,W,3] (else one [H,W,3]), after checking their shapes."""
    if img.shape != ref.shape:
        raise ValueError(f"{what}: image and reference differ in shape: {tuple(img.shape)} vs {tuple(ref.shape)}")
    if img.dim() not in (3, 4) or img.shape[-1] != 3:
        raise ValueError(f"{what}: expected images [H,W,3] or [B,H,W,3], got {tuple(img.shape)}")
    if not img.is_floating_point() or not ref.is_floating_point():
        raise ValueError(f"{what}: expected float images in [0,1], got {img.dtype} and {ref.dtype}")
    return img.dim() == 4


def _as_batch(img: torch.Tensor, ref: torch.Tensor, what: str) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """([B,H,W,3], [B,H,W,3], was_batched) after checking shapes."""
    batched = _check_pair(img, ref, what)
    return (img, ref, True) if batched else (img[None], ref[None], False)


def psnr(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of float images in [0,1] ([H,W,3] -> 0-d, [B,H,W,3] -> [B]); identical images give inf."""
    # one image (a training step's, every step): one op for the mean square, no batch axis added
    mse = (img - ref).square().flatten(1).mean(1) if _check_pair(img, ref, "psnr") else F.mse_loss(img, ref)
    return -10.0 * torch.log10(mse)


_WINDOWS: dict[tuple, torch.Tensor] = {}


def _gaussian_1d(device, dtype) -> torch.Tensor:
    """Normalised 1D Gaussian [11] (sigma 1.5), cached per device and dtype."""
    key = (str(device), dtype)
    w = _WINDOWS.get(key)
    if w is None:
        x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
        g = torch.exp(-x.square() / (2 * SSIM_SIGMA ** 2))
        w = (g / g.sum()).to(device=device, dtype=dtype)
        _WINDOWS[key] = w
    return w


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM [B,3,H,W] of [B,H,W,3] images (zero padding, 3DGS formula)."""
    if _warp_ssim_takes(img, ref):
        return _WarpSSIM.apply(img, ref).permute(0, 3, 1, 2)
    return ssim_map_conv(img, ref)


def _warp_ssim_takes(img: torch.Tensor, ref: torch.Tensor) -> bool:
    """Whether the Warp passes compute SSIM of these images (float32, a constant reference)."""
    return img.dtype == torch.float32 and ref.dtype == torch.float32 and not ref.requires_grad


def ssim_map_conv(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """`ssim_map` as separable convolutions in torch: any dtype, gradients to both images."""
    x = img.permute(0, 3, 1, 2)
    y = ref.permute(0, 3, 1, 2)
    b, c, h, w = x.shape
    g = _gaussian_1d(x.device, x.dtype)
    pad = SSIM_WINDOW // 2
    # five moments, every channel filtered on its own: [B, 5*C, H, W]
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)
    n = stack.shape[1]
    stack = F.conv2d(stack, g.view(1, 1, 1, -1).expand(n, 1, 1, SSIM_WINDOW), padding=(0, pad), groups=n)
    stack = F.conv2d(stack, g.view(1, 1, -1, 1).expand(n, 1, SSIM_WINDOW, 1), padding=(pad, 0), groups=n)
    mu1, mu2, e11, e22, e12 = stack.split(c, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq, sigma2_sq, sigma12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    return ((2 * mu12 + SSIM_C1) * (2 * sigma12 + SSIM_C2)) / \
        ((mu1_sq + mu2_sq + SSIM_C1) * (sigma1_sq + sigma2_sq + SSIM_C2))


def _ssim_passes(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(SSIM per value, like x; its partials [3, n]) of contiguous float32 images [..., H, W, 3]
    through the Warp passes."""
    from tomgs.kernels import ssim as kernels
    from tomgs.runtime import launch, scope, wrap, wrap_flat

    n, (height, width) = x.numel(), x.shape[-3:-1]
    window = _gaussian_1d(x.device, torch.float32)
    moments = torch.empty(5, n, device=x.device, dtype=torch.float32)
    partials = torch.empty(3, n, device=x.device, dtype=torch.float32)
    out = torch.empty_like(x)
    flat = (wrap_flat(x), wrap_flat(y), wrap(window))
    with scope(x.device) as device:
        launch(kernels.moments_rows, n, device=device, args=[*flat, width, wrap(moments)])
        launch(kernels.ssim_cols, n, device=device, args=[
            wrap(moments), flat[2], width, height, SSIM_C1, SSIM_C2, wrap_flat(out), wrap(partials)])
    return out, partials


def _ssim_gradient(x: torch.Tensor, y: torch.Tensor, partials: torch.Tensor, v_ssim: torch.Tensor,
                   v_l1: torch.Tensor | None = None) -> torch.Tensor:
    """dL/dx, like x, from dL/dS per value (`v_ssim` [n], or one value seen through a zero stride)
    and, for a training loss, dL/d|x - y| (`v_l1`, the same way)."""
    from tomgs.kernels import ssim as kernels
    from tomgs.runtime import NO_ARRAY, launch, scope, wrap, wrap_flat

    n, (height, width) = x.numel(), x.shape[-3:-1]
    window = _gaussian_1d(x.device, torch.float32)
    blurred = torch.empty_like(partials)
    v_x = torch.empty_like(x)
    with scope(x.device) as device:
        launch(kernels.grad_rows, n, device=device, args=[
            # an expanded value is 1D with a zero stride; a map is contiguous, any shape
            wrap(v_ssim) if v_ssim.dim() == 1 else wrap_flat(v_ssim), wrap(partials), wrap(window), width,
            wrap(blurred)])
        launch(kernels.grad_cols, n, device=device, args=[
            wrap(blurred), wrap_flat(x), wrap_flat(y), wrap(window), width, height,
            NO_ARRAY if v_l1 is None else wrap(v_l1), wrap_flat(v_x)])
    return v_x


class _WarpSSIM(torch.autograd.Function):
    """Per-pixel SSIM [B,H,W,3] of float32 [B,H,W,3] images (or [H,W,3] of [H,W,3]); gradient to the
    first only."""

    @staticmethod
    def forward(ctx, img, ref):
        x, y = img.contiguous(), ref.contiguous()
        out, partials = _ssim_passes(x, y)
        ctx.save_for_backward(x, y, partials)
        return out

    @staticmethod
    def backward(ctx, v_out):
        x, y, partials = ctx.saved_tensors
        return _ssim_gradient(x, y, partials, v_out.contiguous()), None


class _WarpLoss(torch.autograd.Function):
    """`l1_dssim` of float32 images and a constant reference, and the PSNR of all their values: two
    0-d tensors, the loss's gradient to the image only (the PSNR has none)."""

    @staticmethod
    def forward(ctx, img, ref, ssim_weight: float):
        from tomgs.kernels import ssim as kernels
        from tomgs.runtime import launch, scope, whole_blocks, wrap, wrap_flat

        x, y = img.contiguous(), ref.contiguous()
        n = x.numel()
        out, partials = _ssim_passes(x, y)
        sums = torch.zeros(3, device=x.device, dtype=torch.float32)
        loss = torch.empty((), device=x.device, dtype=torch.float32)
        measured = torch.empty((), device=x.device, dtype=torch.float32)
        with scope(x.device) as device:
            launch(kernels.loss_sums, whole_blocks(n), device=device, args=[
                wrap_flat(x), wrap_flat(y), wrap_flat(out), n, wrap(sums)])
            launch(kernels.combine_loss, 1, device=device, args=[
                wrap(sums), n, float(ssim_weight), wrap(loss), wrap(measured)])
        ctx.save_for_backward(x, y, partials)
        ctx.ssim_weight = float(ssim_weight)
        ctx.mark_non_differentiable(measured)
        return loss, measured

    @staticmethod
    def backward(ctx, v_loss, _v_psnr):
        x, y, partials = ctx.saved_tensors
        n, weight = x.numel(), ctx.ssim_weight
        # uniform upstreams, left on the device: one value each, seen [n] through a zero stride
        v_ssim = (v_loss * (-weight / n)).expand(n)
        v_l1 = (v_loss * ((1.0 - weight) / n)).expand(n)
        return _ssim_gradient(x, y, partials, v_ssim, v_l1), None, None


def l1_dssim(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float) -> torch.Tensor:
    """The 3DGS training loss (1 - w) mean|img - ref| + w (1 - SSIM(img, ref)) of float images in
    [0,1] ([H,W,3] or [B,H,W,3], the means over every value): 0-d. Float32 images with a constant
    reference take the Warp passes, which give the L1 term's gradient with the SSIM's (no torch
    operation over the image); anything else the torch formulas."""
    return l1_dssim_and_psnr(img, ref, ssim_weight)[0]


def training_loss(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float,
                  weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """TOM-GS's training loss and the image's PSNR, the one formula every training step uses:
    (1 - ssim_weight) L1 + ssim_weight D-SSIM of img [H,W,3] against ref [H,W,3]; with `weights` [H,W,1]
    in [0,1], both terms and the PSNR over the weighted pixels. Returns (loss 0-d, PSNR 0-d without
    gradient)."""
    if weights is None:
        return l1_dssim_and_psnr(img, ref, ssim_weight)
    total = 3 * weights.sum().clamp_min(1e-12)
    l1 = (img - ref).abs().sum() / total
    similarity = (ssim_map(img[None], ref[None])[0] * weights.permute(2, 0, 1)).sum() / total
    loss = (1 - ssim_weight) * l1 + ssim_weight * (1 - similarity)
    return loss, weighted_psnr(img.detach(), ref.detach(), weights)


def weighted_psnr(img: torch.Tensor, ref: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """PSNR (0-d) of img [H,W,3] against ref over the pixels weighted by `weights` [H,W,1] in [0,1]."""
    mse = (img - ref).square().sum() / (3 * weights.sum().clamp_min(1e-12))
    return -10.0 * torch.log10(mse)


def l1_dssim_and_psnr(img: torch.Tensor, ref: torch.Tensor, ssim_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(`l1_dssim`, the PSNR of all of img's values against ref's: 0-d, no gradient; for one image
    [H,W,3] `psnr`'s). On the Warp path the PSNR comes from the loss's own sums: a training step
    measures its frame without further operations over the image (each a dispatch of host time)."""
    _check_pair(img, ref, "l1_dssim")
    if _warp_ssim_takes(img, ref):
        return _WarpLoss.apply(img, ref, ssim_weight)
    loss = (1 - ssim_weight) * (img - ref).abs().mean() + ssim_weight * (1 - ssim(img, ref).mean())
    return loss, -10.0 * torch.log10(F.mse_loss(img.detach(), ref.detach()))


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """SSIM of float images in [0,1] ([H,W,3] -> 0-d, [B,H,W,3] -> [B]), mean over pixels and channels.

    Differentiable in both arguments; the D-SSIM loss is 1 - ssim(render, target)."""
    batched = _check_pair(img, ref, "ssim")
    if _warp_ssim_takes(img, ref):
        # the Warp map as it comes, channels last, of one image or a batch: no permuted copy to average
        out = _WarpSSIM.apply(img, ref)
        return out.flatten(1).mean(1) if batched else out.mean()
    x, y, _ = _as_batch(img, ref, "ssim")
    out = ssim_map_conv(x, y).flatten(1).mean(1)
    return out if batched else out[0]


@torch.no_grad()
def frame_psnr(model, frames: torch.Tensor, cameras, device, tick=None) -> list[float]:
    """PSNR [F] of each frame (uint8 [F,H,W,3]) of GaussianModel `model` rendered at its camera and time
    (clip time), one frame at a time: what a fit measures of its own frames."""
    from tomgs.render.frame import rasterize

    viewmats = cameras.viewmats(device)
    K = torch.as_tensor(cameras.K, dtype=torch.float32, device=device)
    inputs = model.render_inputs()
    out = []
    for k in range(len(cameras)):
        image = rasterize(**inputs, viewmat=viewmats[k], K=K, width=cameras.width, height=cameras.height,
                          t=float(cameras.times[k]))[0]
        out.append(psnr(image, frames[k].to(device).float() / 255.0))
        if tick is not None:
            tick(k + 1, len(cameras))
    return torch.stack(out).tolist() if out else []


# -- LPIPS ---------------------------------------------------------------------------------------

_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
# (stride, padding, max-pool after the ReLU) of AlexNet's five convolutions
_ALEX_LAYERS = ((4, 2, True), (1, 2, True), (1, 1, False), (1, 1, False), (1, 1, False))


def default_lpips_weights() -> Path | None:
    """The path in TOMGS_LPIPS_WEIGHTS (a file, or a folder holding alexnet-lpips-v0.1.npz), or None."""
    value = os.environ.get(LPIPS_ENV)
    if not value:
        return None
    path = Path(value)
    return path / "alexnet-lpips-v0.1.npz" if path.is_dir() else path


def lpips_shapes() -> dict[str, tuple[int, ...]]:
    """The array shapes of LPIPS v0.1 AlexNet weights: conv{i}.weight/bias and lin{i}.weight ([C], or
    [1,C,1,1] as LPIPS saves its 1x1 convolutions: any shape of C values is taken)."""
    channels, kernels = (3, 64, 192, 384, 256, 256), (11, 5, 3, 3, 3)
    shapes = {}
    for i in range(5):
        c_in, c_out, k = channels[i], channels[i + 1], kernels[i]
        shapes[f"conv{i}.weight"] = (c_out, c_in, k, k)
        shapes[f"conv{i}.bias"] = (c_out,)
        shapes[f"lin{i}.weight"] = (c_out,)
    return shapes


class LPIPS:
    """LPIPS distance (AlexNet features, linear heads v0.1) from an npz of weights; no downloads.

    `weights_path`: npz with conv{0..4}.weight/bias and lin{0..4}.weight (or a folder holding
    alexnet-lpips-v0.1.npz); None uses $TOMGS_LPIPS_WEIGHTS. Call with images [H,W,3] or
    [B,H,W,3] in [0,1]; returns one distance per image (lower is closer).
    """

    def __init__(self, weights_path=None, device=None):
        from tomgs.errors import InputError
        from tomgs.io.tets import read_npz

        path = Path(weights_path) if weights_path is not None else default_lpips_weights()
        if path is None:
            raise InputError(f"LPIPS needs its weights: pass the path of alexnet-lpips-v0.1.npz or set {LPIPS_ENV}")
        if path.is_dir():
            path = path / "alexnet-lpips-v0.1.npz"
        if not path.is_file():
            raise InputError(f"{path}: LPIPS weights not found; give the path of alexnet-lpips-v0.1.npz "
                             f"(conv0..4 weight/bias, lin0..4 weight)")
        self.path = path
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        fix = "expected conv0..4 weight/bias and lin0..4 weight of LPIPS v0.1 AlexNet (alexnet-lpips-v0.1.npz)"
        shapes = lpips_shapes()

        def check(name, shape, dtype):  # before the member is decompressed: its shape is known in advance
            want = shapes[name]
            if (shape != want and not (name.startswith("lin") and int(np.prod(shape)) == want[0])) \
                    or dtype.kind != "f":
                raise InputError(f"{path}: {name} is {dtype} {list(shape)}, LPIPS AlexNet needs float {list(want)}; "
                                 f"{fix}")

        data = read_npz(path, check, list(shapes), f"not an LPIPS weights file; {fix}", required=list(shapes))
        arrays = {k: torch.as_tensor(np.asarray(v, dtype=np.float32), device=self.device) for k, v in data.items()}
        bad = [k for k, v in arrays.items() if not bool(torch.isfinite(v).all())]
        if bad:
            raise InputError(f"{path}: non-finite values in {', '.join(bad)}; {fix}")
        self.convs = [(arrays[f"conv{i}.weight"], arrays[f"conv{i}.bias"]) for i in range(5)]
        self.lins = [arrays[f"lin{i}.weight"].view(1, -1, 1, 1) for i in range(5)]
        self.shift = torch.tensor(_LPIPS_SHIFT, device=self.device).view(1, 3, 1, 1)
        self.scale = torch.tensor(_LPIPS_SCALE, device=self.device).view(1, 3, 1, 1)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """AlexNet features after each of the 5 ReLUs of [B,3,H,W] images in [0,1]."""
        h = ((x * 2 - 1) - self.shift) / self.scale
        feats = []
        for (w, b), (stride, padding, pool) in zip(self.convs, _ALEX_LAYERS):
            h = F.relu(F.conv2d(h, w, b, stride=stride, padding=padding))
            feats.append(h)
            if pool:
                h = F.max_pool2d(h, kernel_size=3, stride=2)
        return feats

    def __call__(self, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        x, y, batched = _as_batch(img, ref, "lpips")
        x = x.to(self.device, torch.float32).permute(0, 3, 1, 2)
        y = y.to(self.device, torch.float32).permute(0, 3, 1, 2)
        total = 0.0
        for fx, fy, lin in zip(self.features(x), self.features(y), self.lins):
            fx = fx / (fx.square().sum(1, keepdim=True).sqrt() + 1e-10)
            fy = fy / (fy.square().sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + ((fx - fy).square() * lin).sum(1).mean((1, 2))
        return total if batched else total[0]


# -- evaluation of a fitted scene -----------------------------------------------------------------

@dataclass
class EvalReport:
    """Per-frame metrics of a scene against its clip; `frames` are the evaluated frame indices."""

    frames: list[int]
    psnr: list[float]
    ssim: list[float]
    lpips: list[float] | None = None
    seconds: float = 0.0
    width: int = 0
    height: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def mean_psnr(self) -> float:
        return float(np.mean(self.psnr)) if self.psnr else float("nan")

    @property
    def mean_ssim(self) -> float:
        return float(np.mean(self.ssim)) if self.ssim else float("nan")

    @property
    def mean_lpips(self) -> float | None:
        return float(np.mean(self.lpips)) if self.lpips else None

    def to_dict(self) -> dict:
        """JSON-ready: means and per-frame lists."""
        out = dict(frames=len(self.frames), width=self.width, height=self.height, seconds=self.seconds,
                   psnr=self.mean_psnr, ssim=self.mean_ssim,
                   per_frame=[dict(frame=k, psnr=p, ssim=s) for k, p, s in zip(self.frames, self.psnr, self.ssim)])
        if self.lpips is not None:
            out["lpips"] = self.mean_lpips
            for row, v in zip(out["per_frame"], self.lpips):
                row["lpips"] = v
        return out

    def summary(self) -> str:
        text = f"{counted(len(self.frames), 'frame')} at {self.width}x{self.height}: PSNR {self.mean_psnr:.2f} dB, " \
               f"SSIM {self.mean_ssim:.4f}"
        if self.lpips is not None:
            text += f", LPIPS {self.mean_lpips:.4f}"
        return text + f" ({self.seconds:.1f} s)"


def evaluate(model, cameras, frames, indices=None, lpips: LPIPS | None = None, device=None) -> EvalReport:
    """Render `model` (a GaussianModel, or a mapping of rasterizer inputs) at `cameras` and compare with
    `frames`, frame k of the cameras against frame k of the clip.

    `frames`: uint8 [T,H,W,3] RGB, float [T,H,W,3] in [0,1], or a tomgs Video. Renders are compared
    as floats (no 8-bit rounding); note that 8-bit references alone bound PSNR near 59 dB.
    `indices`: the frames to evaluate (default all); `lpips`: an LPIPS instance to add that metric;
    `device`: where to render and measure (default: where the model lives). Raises ValueError on
    mismatched sizes, counts or indices."""
    from tomgs.render.sequence import render_sequence

    clip = getattr(frames, "frames", frames)
    if isinstance(clip, torch.Tensor):
        clip = clip.detach().cpu().numpy()
    clip = np.asarray(clip)
    if clip.ndim != 4 or clip.shape[-1] != 3 or not (clip.dtype == np.uint8 or np.issubdtype(clip.dtype, np.floating)):
        raise ValueError(f"evaluate: frames must be uint8 or float [T,H,W,3] RGB (or a tomgs Video), got "
                         f"{clip.dtype} {clip.shape}")
    T, H, W = clip.shape[:3]
    if (H, W) != (cameras.height, cameras.width):
        raise ValueError(f"evaluate: frames are {W}x{H} but the cameras render {cameras.width}x{cameras.height}; "
                         f"read the video at the scene's size (or resize the cameras)")
    if T != len(cameras):
        raise ValueError(f"evaluate: {T} frames but {len(cameras)} cameras; evaluate the clip the scene was fitted to")
    indices = list(range(T)) if indices is None else [int(k) for k in indices]
    bad = [k for k in indices if not 0 <= k < T]
    if bad:
        raise ValueError(f"evaluate: frame indices {bad[:5]} out of range 0..{T - 1}")
    gaussians = model.render_inputs() if hasattr(model, "render_inputs") else model
    dev = torch.device(device) if device is not None else gaussians["means"].device
    scale = 1.0 / 255.0 if clip.dtype == np.uint8 else 1.0
    start = time.perf_counter()
    report = EvalReport(frames=[], psnr=[], ssim=[], lpips=[] if lpips is not None else None, width=W, height=H)
    with torch.no_grad():
        for k, image, _ in render_sequence(gaussians, cameras, indices, device=dev):
            img = image.to(dev)
            ref = torch.from_numpy(np.ascontiguousarray(clip[k])).to(dev).float() * scale
            report.frames.append(k)
            report.psnr.append(float(psnr(img, ref)))
            report.ssim.append(float(ssim(img, ref)))
            if lpips is not None:
                report.lpips.append(float(lpips(img, ref)))
    report.seconds = time.perf_counter() - start
    return report


__all__ = ["psnr", "training_loss", "weighted_psnr", "ssim", "ssim_map", "ssim_map_conv", "LPIPS", "EvalReport", "evaluate", "default_lpips_weights",
           "frame_psnr"]


# ---- what a compressed copy of a scene loses ------------------------------------------------------

def loss_db(scene_psnr: float, copy_psnr: float) -> float:
    """dB the scene's PSNR against its clip falls when a copy renders at `copy_psnr` against the
    scene's own renders: their errors add (independent), 10 log10(1 + 10^((scene - copy) / 10))."""
    return float(10.0 * np.log10(1.0 + 10.0 ** ((scene_psnr - copy_psnr) / 10.0)))


def required_copy_psnr(scene_psnr: float, max_loss_db: float) -> float:
    """The PSNR against the scene's renders a copy needs to lose at most `max_loss_db` (> 0) of
    `scene_psnr`: the inverse of `loss_db` (0.2 dB: 13.3 dB above the scene's PSNR)."""
    with np.errstate(divide="ignore"):  # a loss too small for a float64 asks for an infinite PSNR
        return float(scene_psnr - 10.0 * np.log10(np.expm1(max_loss_db / 10.0 * np.log(10.0))))


def copy_psnr(model, copy, cameras, frames: int = 4, max_side: int = 1024, device=None) -> float:
    """PSNR (dB) of `copy`'s renders (a GaussianModel: a decoded .tsog) against `model`'s at
    `frames` frames spread over `cameras` (first to last), at most `max_side` pixels a side: the
    mean squared error over all of them, so a frame where both are black does not count as infinite.
    Both models' Gaussians in the same clip."""
    from tomgs.render.sequence import render_sequence

    scale = min(1.0, max_side / max(cameras.width, cameras.height))
    small = cameras.resized(max(1, round(cameras.width * scale)), max(1, round(cameras.height * scale)))
    indices = sorted(set(np.linspace(0, len(cameras) - 1, max(1, min(frames, len(cameras)))).round().astype(int)))
    total = 0.0
    for (_, a, _), (_, b, _) in zip(render_sequence(model.render_inputs(), small, indices, device=device),
                                    render_sequence(copy.render_inputs(), small, indices, device=device)):
        total += float(((a.double() - b.double()) ** 2).mean())
    mse = total / len(indices)
    return float("inf") if mse == 0 else float(-10.0 * np.log10(mse))
