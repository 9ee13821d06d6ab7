"""PSNR, SSIM (3DGS formula, zero padding), LPIPS check values, and evaluate() of a rendered scene."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from scenes import devices
from tomgs.metrics import LPIPS, evaluate, l1_dssim, l1_dssim_and_psnr, psnr, ssim, ssim_map, ssim_map_conv

LPIPS_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lpips"


def test_psnr_of_known_noise():
    g = torch.Generator().manual_seed(0)
    ref = torch.full((64, 64, 3), 0.5)
    noise = torch.randn(64, 64, 3, generator=g) * 0.05
    img = ref + noise
    expected = -10 * math.log10(float(noise.square().mean()))
    assert abs(float(psnr(img, ref)) - expected) < 1e-4
    assert 25.5 < expected < 26.5  # sigma 0.05 -> about 26 dB
    assert float(psnr(ref + 0.1, ref)) == pytest.approx(20.0, abs=1e-4)
    assert math.isinf(float(psnr(ref, ref)))
    batch = psnr(torch.stack([ref + 0.1, ref + 0.01]), torch.stack([ref, ref]))
    assert batch.shape == (2,) and torch.allclose(batch, torch.tensor([20.0, 40.0]), atol=1e-3)


def _ssim_direct(x: np.ndarray, y: np.ndarray) -> float:
    """The same formula written out independently: full 2D window, zero padding, float64 loops."""
    r = np.arange(11) - 5
    g = np.exp(-(r ** 2) / (2 * 1.5 ** 2))
    g /= g.sum()
    w = np.outer(g, g)
    h, wd, c = x.shape

    def filt(a):
        p = np.zeros((h + 10, wd + 10, c))
        p[5:5 + h, 5:5 + wd] = a
        out = np.zeros_like(a)
        for i in range(11):
            for j in range(11):
                out += w[i, j] * p[i:i + h, j:j + wd]
        return out

    mu1, mu2 = filt(x), filt(y)
    s11, s22, s12 = filt(x * x) - mu1 ** 2, filt(y * y) - mu2 ** 2, filt(x * y) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))
    return float(m.mean())


def test_ssim_identical_is_one_and_matches_direct_formula():
    rng = np.random.default_rng(1)
    x = rng.random((23, 31, 3))
    assert float(ssim(torch.tensor(x), torch.tensor(x))) == pytest.approx(1.0, abs=1e-12)
    for k in range(3):
        a = rng.random((20 + k, 27, 3))
        b = np.clip(a + rng.normal(0, 0.1 * (k + 1), a.shape), 0, 1)
        direct = _ssim_direct(a, b)
        assert abs(float(ssim(torch.tensor(a), torch.tensor(b))) - direct) < 1e-6
        got32 = float(ssim(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32)))
        assert abs(got32 - direct) < 1e-4


def test_ssim_batched_matches_single():
    rng = np.random.default_rng(2)
    a, b = torch.tensor(rng.random((3, 16, 18, 3))), torch.tensor(rng.random((3, 16, 18, 3)))
    batch = ssim(a, b)
    assert batch.shape == (3,)
    for i in range(3):
        assert float(batch[i]) == pytest.approx(float(ssim(a[i], b[i])), abs=1e-12)


def test_ssim_decreases_with_noise():
    g = torch.Generator().manual_seed(3)
    ref = torch.rand(48, 48, 3, generator=g)
    ref = torch.nn.functional.avg_pool2d(ref.permute(2, 0, 1)[None], 5, 1, 2)[0].permute(1, 2, 0)  # some structure
    noise = torch.randn(48, 48, 3, generator=g)
    values = [float(ssim((ref + s * noise).clamp(0, 1), ref)) for s in (0.0, 0.02, 0.05, 0.1, 0.2)]
    assert values[0] == pytest.approx(1.0, abs=1e-6)
    assert all(a > b for a, b in zip(values, values[1:])), values


def test_ssim_is_differentiable():
    g = torch.Generator().manual_seed(4)
    a = torch.rand(7, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(7, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(ssim, (a, b), eps=1e-6, atol=1e-6, fast_mode=True)
    assert torch.autograd.gradcheck(ssim, (a[:4, :3].detach().requires_grad_(), b[:4, :3].detach()), eps=1e-6, atol=1e-6)
    loss = 1 - ssim(a, b)
    loss.backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


def _ssim_cases(seed: int):
    """Fresh random [B,H,W,3] pairs in [0,1], extremes included: images smaller than the window, a
    single pixel, constant (zero-variance) and saturated images, and near-identical pairs."""
    g = torch.Generator().manual_seed(seed)
    for shape in ((1, 19, 26, 3), (2, 12, 9, 3), (1, 4, 3, 3), (1, 1, 1, 3)):
        a = torch.rand(shape, generator=g, dtype=torch.float64)
        yield a, (a + 0.2 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    shape = (1, 14, 15, 3)
    noise = torch.randn(shape, generator=g, dtype=torch.float64)
    yield torch.zeros(shape, dtype=torch.float64), torch.ones(shape, dtype=torch.float64)  # constant, opposite
    yield torch.ones(shape, dtype=torch.float64), (1 - 0.05 * noise.abs()).clamp(0, 1)  # saturated
    a = torch.rand(shape, generator=g, dtype=torch.float64)
    yield a, (a + 1e-4 * noise).clamp(0, 1)  # almost identical: S near 1, gradients near 0


def test_warp_ssim_matches_the_float64_reference():
    """The float32 Warp passes (values and gradient to the image) against float64 convolutions."""
    for seed in (5, 6):
        for a, b in _ssim_cases(seed):
            x = a.float().requires_grad_(True)
            upstream = torch.randn(a.shape[0], 3, *a.shape[1:3], generator=torch.Generator().manual_seed(seed),
                                   dtype=torch.float64)
            got = ssim_map(x, b.float())
            (got * upstream.float()).sum().backward()
            ref64 = a.clone().requires_grad_(True)
            want = ssim_map_conv(ref64, b)
            (want * upstream).sum().backward()
            assert got.shape == want.shape
            assert torch.isfinite(got).all() and torch.isfinite(x.grad).all()
            # float32 bound: the torch convolutions in float32 (cancellation in e11 - mu1^2 on bright
            # flat patches costs both about 1e-4), or 2e-5 where they do better than that
            x32 = a.float().requires_grad_(True)
            conv32 = ssim_map_conv(x32, b.float())
            (conv32 * upstream.float()).sum().backward()
            value_tol = max(2e-5, 2 * float((conv32.double() - want).abs().max()))
            grad_tol = max(2e-5 * float(ref64.grad.abs().max().clamp_min(1.0)),
                           2 * float((x32.grad.double() - ref64.grad).abs().max()))
            assert (got.double() - want).abs().max() <= value_tol, a.shape
            assert (x.grad.double() - ref64.grad).abs().max() <= grad_tol, a.shape


def test_one_image_takes_the_training_path_with_the_batchs_values_and_gradients():
    """A training step's SSIM and PSNR of one float32 [H,W,3] image (no batch axis, no permuted copy,
    one op for the mean square) against the same image as a batch of one and the float64 reference."""
    g = torch.Generator().manual_seed(8)
    a = torch.rand(21, 17, 3, generator=g)
    b = (a + 0.1 * torch.randn(21, 17, 3, generator=g)).clamp(0, 1)
    one = a.clone().requires_grad_(True)
    (0.7 * ssim(one, b)).backward()
    batch = a[None].clone().requires_grad_(True)
    (0.7 * ssim(batch, b[None])).sum().backward()
    ref64 = a.double().requires_grad_(True)
    want = ssim(ref64, b.double())
    (0.7 * want).backward()
    assert ssim(one, b).shape == () and float(ssim(one, b)) == pytest.approx(float(ssim(batch, b[None])[0]), abs=1e-7)
    assert float(ssim(one, b)) == pytest.approx(float(want), abs=2e-6)
    assert torch.allclose(one.grad, batch.grad[0], rtol=1e-6, atol=1e-9)
    assert (one.grad.double() - ref64.grad).abs().max() <= 1e-5 * float(ref64.grad.abs().max())
    single, batched = psnr(a, b), psnr(a[None], b[None])
    assert single.shape == () and float(single) == pytest.approx(float(batched[0]), abs=1e-4)
    assert float(single) == pytest.approx(float(-10 * torch.log10((a.double() - b.double()).square().mean())), abs=1e-4)


@pytest.mark.parametrize("weight", [0.2, 0.0, 1.0])
def test_the_training_loss_in_the_ssim_passes_matches_the_float64_formula(weight):
    """l1_dssim's Warp path (float32, the L1 term's gradient inside the SSIM backward, the loss's
    upstream never read on the host) against (1 - w) L1 + w (1 - SSIM) in float64, values and
    gradients, on fresh random images and the extremes (smaller than the window, one pixel, equal
    images: |d|' = 0 as torch takes it, constant and saturated ones), single and batched."""
    for seed in (9, 10):
        cases = [(a[0], b[0]) for a, b in _ssim_cases(seed)] + [(a, b) for a, b in _ssim_cases(seed + 100)][:2]
        equal = torch.rand(9, 11, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        cases.append((equal, equal.clone()))
        for a, b in cases:
            x = a.float().requires_grad_(True)
            got = l1_dssim(x, b.float(), weight)
            (3.0 * got).backward()  # an upstream other than 1
            ref64 = a.clone().requires_grad_(True)
            similarity = ssim(ref64, b).mean()
            want = (1 - weight) * (ref64 - b).abs().mean() + weight * (1 - similarity)
            (3.0 * want).backward()
            # float32 bound as for ssim_map: the torch formula in float32 (conv cancellation on bright
            # flat patches), or 2e-5 where it does better
            x32 = a.float().requires_grad_(True)
            batch = (-1, *a.shape[-3:])
            torch32 = (1 - weight) * (x32 - b.float()).abs().mean() + weight * (1 - ssim_map_conv(
                x32.reshape(batch), b.float().reshape(batch)).mean())
            (3.0 * torch32).backward()
            value_tol = max(2e-6, 2 * abs(float(torch32) - float(want)))
            grad_tol = max(2e-5 * float(ref64.grad.abs().max().clamp_min(1.0)),
                           2 * float((x32.grad.double() - ref64.grad).abs().max()))
            assert got.shape == () and got.dtype == torch.float32
            assert abs(float(got) - float(want)) <= value_tol, a.shape
            assert (x.grad.double() - ref64.grad).abs().max() <= grad_tol, a.shape
    # anything but float32 with a constant reference: the torch formula, gradients to both
    a64 = torch.rand(6, 7, 3, dtype=torch.float64, requires_grad=True)
    b64 = torch.rand(6, 7, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p, q: l1_dssim(p, q, 0.2), (a64, b64), eps=1e-6, atol=1e-6, fast_mode=True)


@pytest.mark.parametrize("device", devices())
def test_the_training_loss_measures_its_psnr_from_its_own_sums(device):
    """l1_dssim_and_psnr: the loss as l1_dssim gives it, and the PSNR of all values as psnr computes
    it in float64 (on the Warp path from the loss's sums, in float32: within 1e-4 dB), on fresh random
    images and the extremes (one pixel, a near-identical pair at ~90 dB, equal images: inf), single and
    batched; no gradient reaches the image through the PSNR. The torch path (float64) gives the same.
    On every device the tests run on (a GPU sums in blocks of 256 threads)."""
    for seed in (21, 22):
        cases = [(a[0], b[0]) for a, b in _ssim_cases(seed)] + [(a, b) for a, b in _ssim_cases(seed + 100)][:2]
        for a, b in cases:
            a, b = a.to(device), b.to(device)
            want = float(-10 * torch.log10((a - b).square().mean()))
            for x, y in ((a.float(), b.float()), (a, b)):  # the Warp passes, then the torch formulas
                x = x.clone().requires_grad_(True)
                loss, measured = l1_dssim_and_psnr(x, y, 0.2)
                assert measured.shape == () and not measured.requires_grad
                assert float(measured) == pytest.approx(want, abs=1e-4 if x.dtype == torch.float32 else 1e-9)
                # a GPU adds its block sums in any order: equal to float32 rounding
                assert float(loss) == pytest.approx(float(l1_dssim(x.detach(), y, 0.2)), rel=1e-6, abs=1e-7)
                loss.backward()
                assert torch.isfinite(x.grad).all()
        same = torch.rand(5, 6, 3, generator=torch.Generator().manual_seed(seed)).to(device)
        assert float(l1_dssim_and_psnr(same, same.clone(), 0.2)[1]) == float("inf")


def test_the_training_losss_block_sums_hold_in_cooperative_blocks(monkeypatch):
    """The loss's sums run per block of 256 threads on a GPU (a block sum, one atomic per block, the
    last block partly past the image): the same on the CPU in 256 cooperative fibers as one thread a
    block, for an image whose values do not fill whole blocks."""
    import warp as wp

    from tomgs import runtime

    g = torch.Generator().manual_seed(12)
    a, b = torch.rand(13, 11, 3, generator=g), torch.rand(13, 11, 3, generator=g)  # 429 values
    alone, alone_psnr = l1_dssim_and_psnr(a, b, 0.2)
    monkeypatch.setattr(runtime, "launch", runtime.Launches())  # launches recorded afresh, as fibers
    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    together, together_psnr = l1_dssim_and_psnr(a, b, 0.2)
    assert float(together) == pytest.approx(float(alone), rel=1e-6)
    assert float(together_psnr) == pytest.approx(float(psnr(a.double(), b.double())), abs=1e-4)
    assert float(together_psnr) == pytest.approx(float(alone_psnr), abs=1e-5)
    want = 0.8 * (a.double() - b.double()).abs().mean() + 0.2 * (1 - ssim(a.double(), b.double()))
    assert float(together) == pytest.approx(float(want), abs=1e-5)


def test_metrics_reject_bad_shapes():
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(torch.zeros(8, 8, 3), torch.zeros(8, 9, 3))
    with pytest.raises(ValueError, match=r"\[H,W,3\]"):
        psnr(torch.zeros(8, 8), torch.zeros(8, 8))


def _load_rgb(path: Path) -> torch.Tensor:
    import cv2

    return torch.from_numpy(np.ascontiguousarray(cv2.imread(str(path))[..., ::-1])).float() / 255.0


@pytest.mark.skipif(not (LPIPS_DIR / "alexnet-lpips-v0.1.npz").is_file(),
                    reason=f"LPIPS weights folder {LPIPS_DIR} is absent (it sits beside the clone in CI)")
def test_lpips_check_values(monkeypatch):
    metric = LPIPS(LPIPS_DIR / "alexnet-lpips-v0.1.npz")
    ref = _load_rgb(LPIPS_DIR / "ex_ref.png")
    p0, p1 = _load_rgb(LPIPS_DIR / "ex_p0.png"), _load_rgb(LPIPS_DIR / "ex_p1.png")
    assert float(metric(p0, ref)) == pytest.approx(0.7219, abs=1e-4)
    assert float(metric(p1, ref)) == pytest.approx(0.1376, abs=1e-4)
    assert float(metric(ref, ref)) == pytest.approx(0.0, abs=1e-6)
    batch = metric(torch.stack([p0, p1]), torch.stack([ref, ref]))
    assert torch.allclose(batch, torch.tensor([0.7219, 0.1376]), atol=1e-4)
    monkeypatch.setenv("TOMGS_LPIPS_WEIGHTS", str(LPIPS_DIR))  # a folder works, as does the file
    assert float(LPIPS()(p1, ref)) == pytest.approx(0.1376, abs=1e-4)


def test_lpips_needs_weights(tmp_path, monkeypatch):
    monkeypatch.delenv("TOMGS_LPIPS_WEIGHTS", raising=False)
    with pytest.raises(ValueError, match="TOMGS_LPIPS_WEIGHTS"):
        LPIPS()
    with pytest.raises(ValueError, match="not found"):
        LPIPS(tmp_path / "nothing.npz")
    np.savez(tmp_path / "bad.npz", x=np.zeros(3))
    with pytest.raises(ValueError, match="not an LPIPS weights file"):
        LPIPS(tmp_path / "bad.npz")


# -- evaluate -------------------------------------------------------------------------------------

def _tiny_scene(n_points: int = 300, frames: int = 4, width: int = 48, height: int = 32):
    from tomgs.cameras import Cameras, intrinsics
    from tomgs.model import GaussianModel

    g = torch.Generator().manual_seed(5)
    points = torch.rand(n_points, 3, generator=g) * torch.tensor([3.0, 2.0, 1.0]) + torch.tensor([-1.5, -1.0, 3.0])
    colors = torch.rand(n_points, 3, generator=g)
    t_means = torch.rand(n_points, generator=g)
    model = GaussianModel.from_points(points, colors, t_means, t_scale=0.3, max_sh_degree=0, opacity=0.8)
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    c2w[:, 0, 3] = np.linspace(0.0, 0.1, frames)  # a small sideways dolly
    cams = Cameras.create(c2w, intrinsics(40.0, width, height), width, height)
    return model, cams


def _render_all(model, cams) -> np.ndarray:
    from tomgs.render.sequence import render_sequence

    return np.stack([img.numpy() for _, img, _ in render_sequence(model.render_inputs(), cams, device="cpu")])


def test_evaluate_on_frames_rendered_from_the_same_model():
    model, cams = _tiny_scene()
    rendered = _render_all(model, cams)
    assert rendered.std() > 0.05  # a picture, not a blank
    report = evaluate(model, cams, rendered, device="cpu")  # float frames: no rounding
    assert report.frames == [0, 1, 2, 3] and len(report.psnr) == len(report.ssim) == 4
    assert report.mean_psnr > 60 and all(p > 60 for p in report.psnr)
    assert report.mean_ssim == pytest.approx(1.0, abs=1e-5)
    assert report.lpips is None and report.seconds > 0

    frames_u8 = np.round(rendered * 255).astype(np.uint8)  # 8-bit rounding bounds PSNR near 59 dB
    report8 = evaluate(model, cams, frames_u8, indices=[1, 3], device="cpu")
    assert report8.frames == [1, 3]
    assert report8.mean_psnr > 50 and report8.mean_ssim > 0.999
    d = report8.to_dict()
    assert d["frames"] == 2 and len(d["per_frame"]) == 2 and "PSNR" in report8.summary()


def test_evaluate_tells_a_wrong_model_apart():
    model, cams = _tiny_scene()
    rendered = _render_all(model, cams)
    with torch.no_grad():
        model.sh_dc += 0.3  # every colour brighter
    report = evaluate(model, cams, rendered, device="cpu")
    assert report.mean_psnr < 40 and report.mean_ssim < 0.999


def test_evaluate_accepts_a_video_and_checks_sizes():
    from tomgs.io import Video

    model, cams = _tiny_scene()
    frames_u8 = np.round(_render_all(model, cams) * 255).astype(np.uint8)
    video = Video(frames=frames_u8, masks=None, fps=None, indices=np.arange(4), path=Path("tiny"))
    assert evaluate(model, cams, video, device="cpu").mean_psnr > 50
    with pytest.raises(ValueError, match="cameras render 48x32"):
        evaluate(model, cams, frames_u8[:, :16], device="cpu")
    with pytest.raises(ValueError, match="4 cameras"):
        evaluate(model, cams, frames_u8[:3], device="cpu")
    with pytest.raises(ValueError, match="out of range"):
        evaluate(model, cams, frames_u8, indices=[4], device="cpu")
    with pytest.raises(ValueError, match="uint8 or float"):
        evaluate(model, cams, frames_u8.astype(np.int32), device="cpu")
