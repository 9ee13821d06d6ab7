"""Leaving out what a scene does not need: `tomgs.render.blend_weights` (each Gaussian's pixels' worth
of colour in a frame) against the float64 reference, and the end of a run dropping the Gaussians that
give no frame `compact_pixels` of a pixel, without changing what the scene renders."""

from __future__ import annotations

import pytest
import torch

import tomgs
from tomgs.render.frame import blend_weights
from scenes import devices, random_scene

GEOMETRY = ("means", "quats", "scales", "opacities", "t_means", "t_scales")


def reference_weights(scene: dict) -> torch.Tensor:
    """The float64 reference's d(sum of the red channel) / d(red of each Gaussian): its blend weights summed."""
    ones = torch.ones(scene["means"].shape[0], 3, dtype=torch.float64, requires_grad=True)
    image, _, _ = tomgs.rasterize_reference(**{k: scene[k].double() for k in GEOMETRY}, colors=ones,
                                            viewmat=scene["viewmat"], K=scene["K"], width=scene["width"],
                                            height=scene["height"], t=scene["t"])
    image[..., 0].sum().backward()
    return ones.grad[:, 0]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("device", devices())
def test_blend_weights_are_the_references(seed, device):
    """Fresh random scenes (overlapping clusters, Gaussians off screen, behind the camera, at the near
    plane), one with extreme opacities and scales: the oracle's gradient tolerance."""
    scene = random_scene(seed, n=300)
    if seed == 3:  # nearly opaque and nearly transparent, needles and blobs
        g = torch.Generator().manual_seed(7)
        scene["opacities"] = torch.where(torch.rand(300, generator=g) < 0.5, 0.999, 0.004).double()
        scene["scales"] = scene["scales"] * torch.exp(torch.randn(300, 3, generator=g, dtype=torch.float64) * 2)
    scene = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    scene["t"] = float(torch.tensor(scene["t"], dtype=torch.float32))
    want = reference_weights(scene)
    frame = dict(viewmat=scene["viewmat"].float().to(device), K=scene["K"].float().to(device), width=scene["width"],
                 height=scene["height"], t=scene["t"])
    gaussians = {k: scene[k].float().to(device) for k in GEOMETRY}
    got = blend_weights(**gaussians, **frame)
    assert got.shape == want.shape and float(want.max()) > 1.0 and int((want == 0).sum()) > 0
    torch.testing.assert_close(got.double().cpu(), want, rtol=1e-3, atol=1e-3 * float(want.abs().max()))
    assert torch.equal(got.cpu() == 0, want == 0)  # culled and hidden ones give exactly nothing
    # the same frame, some rows: theirs, and 0 for the others
    rows = torch.arange(0, 300, 3, device=device)
    some = blend_weights(**gaussians, **frame, rows=rows)
    assert some.shape == (300,) and float(some[1::3].abs().max()) == 0.0


def fitted(compact_pixels: float, iterations: int = 150):
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer

    images, cams, points, colors = synthetic_clip(3, 32, 18)
    torch.manual_seed(0)
    trainer = Trainer(images, cams, points, colors, small_config(iterations, compact_pixels=compact_pixels), CPU)
    return trainer, trainer.run()


@pytest.mark.slow  # a long fit
def test_a_run_ends_leaving_out_what_no_frame_shows():
    """The compacted scene renders every frame as the full one does, within what the dropped Gaussians
    gave (each under compact_pixels of a pixel's colour), and its final PSNR is its own."""
    trainer_full, full = fitted(0.0)
    trainer, compact = fitted(0.05)
    assert len(full.model) == len(trainer_full.model) and not any("gave no frame" in n for n in full.notes)
    removed = len(full.model) - len(compact.model)
    assert removed > 0 and any(f"left out {removed:,} Gaussians" in n for n in compact.notes)
    # the same run up to the end: the kept rows are the full model's rows
    kept = {k: v.detach() for k, v in full.model.parameters_by_name().items()}
    inputs = {k: v.detach() for k, v in full.model.render_inputs().items() if k != "colors"}
    frames = [dict(viewmat=trainer.viewmats[k], K=trainer.K, width=32, height=18, t=trainer.times[k]) for k in range(3)]
    weights = torch.stack([blend_weights(**inputs, **frame) for frame in frames])  # [frames, N]
    keep = weights.amax(0) >= 0.05
    assert int(keep.sum()) == len(compact.model)
    for name, value in compact.model.parameters_by_name().items():
        assert torch.equal(value.detach(), kept[name][keep]), name
    # a dropped Gaussian of weight w at a pixel moves a channel there by at most 2 w max|c| (its own
    # colour gone, the ones behind it seen through it again): summed over the frame's pixels, at most
    # 2 max|c| times the dropped Gaussians' blend weights at that frame
    with torch.no_grad():
        bright = 0.2821 * float(full.model.sh_dc.abs().max()) + 0.5  # degree 0: rgb = C0 dc + 0.5
        for frame, weight in zip(frames, weights):
            dropped = float(weight[~keep].sum())
            a, b = (tomgs.rasterize(**m.render_inputs(), **frame)[0] for m in (full.model, compact.model))
            moved = (a - b).abs().sum(dim=(0, 1))  # [3]: each channel, summed over the pixels
            assert 0 < float(moved.max()) <= 2 * bright * dropped
    assert abs(compact.clip_psnr - full.clip_psnr) < 0.05
    # measured after it (the CSV's 3 places)
    assert compact.clip_psnr == pytest.approx(sum(trainer.clip_psnr()) / 3, abs=1e-3)


def test_an_interrupted_run_leaves_nothing_out(tmp_path, monkeypatch):
    """Ctrl-C saves the run as it is (it may resume); only a run that reaches its end compacts, once."""
    from tests.train.test_train import run_clip
    from tomgs.train import Trainer

    calls = []
    compact = Trainer.compact
    monkeypatch.setattr(Trainer, "compact", lambda self, tick=None: calls.append(self.iteration) or compact(self, tick))
    with pytest.raises(KeyboardInterrupt):
        run_clip(100, interrupt_at=50, checkpoint=tmp_path / "run.ckpt")
    assert calls == []
    run_clip(100, checkpoint=tmp_path / "run.ckpt", resume_from=tmp_path / "run.ckpt")
    assert calls == [100]
