"""Frames that do not wait for their counts (tomgs.render.render_frame(defer=True), what render_sequence
pipelines on a GPU): the keys are padded to the bound and sorted whole, the counts are read later.
They must render exactly what a frame that waits renders, say when their keys overflowed, and raise
the same errors when their counts are read."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import tomgs
from tomgs.render import frame as render
from tomgs.cameras import Cameras
from tomgs.render.inputs import RenderError
from tomgs.render.sequence import render_sequence
from scenes import devices, random_scene

DEVICES = devices()
NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")


def scene_on(device: str, seed: int = 4, n: int = 400, width: int = 45, height: int = 37):
    scene = random_scene(seed, n=n, width=width, height=height)
    gaussians = {name: scene[name].float().to(device) for name in NAMES}
    camera = dict(viewmat=scene["viewmat"].float().to(device), K=scene["K"].float().to(device), width=width,
                  height=height)
    return scene, gaussians, camera


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_that_does_not_wait_renders_what_one_that_waits_does(device, fresh_bounds):
    _, gaussians, camera = scene_on(device)
    for t in (0.2, 0.5):
        want, want_alpha, want_meta = tomgs.rasterize(**gaussians, **camera, t=t)
        image, alpha, meta, counts = render.render_frame(**gaussians, **camera, t=t, defer=True)
        assert counts is not None and "n_intersections" not in meta  # counted, so it did not wait
        assert torch.equal(image, want) and torch.equal(alpha, want_alpha)
        assert not counts.overflowed
        assert counts.read() == {k: want_meta[k] for k in ("n_visible", "n_alive", "n_intersections")}
        assert counts.capacity > want_meta["n_intersections"] > 0  # the padding was sorted too


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_of_a_size_not_counted_yet_waits(device, fresh_bounds):
    _, gaussians, camera = scene_on(device)
    image, _, meta, counts = render.render_frame(**gaussians, **camera, t=0.5, defer=True)
    assert counts is None and meta["n_intersections"] > 0
    assert fresh_bounds.capacity(render.Frame(45, 37, 0, 0, 0.01, 1e10, "cpu" if device == "cpu" else
                                               f"cuda:{torch.device(device).index or 0}")) > 0


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_past_its_bound_says_so(device, fresh_bounds):
    _, gaussians, camera = scene_on(device)
    want, _, want_meta = tomgs.rasterize(**gaussians, **camera, t=0.5)
    key = next(iter(fresh_bounds._capacity))
    total = want_meta["n_intersections"]
    fresh_bounds._capacity[key] = total // 3  # as if recent frames had needed a third of it
    image, _, _, counts = render.render_frame(**gaussians, **camera, t=0.5, defer=True)
    assert counts.overflowed and counts.read()["n_intersections"] == total
    assert not torch.equal(image, want)  # the last Gaussians' entries were not written
    assert fresh_bounds.capacity(render.Frame(45, 37, 0, 0, 0.01, 1e10, key[0])) > total  # and the bound grew


@pytest.mark.parametrize("device", DEVICES)
def test_inputs_outside_the_contract_raise_when_the_counts_are_read(device, fresh_bounds):
    _, gaussians, camera = scene_on(device)
    tomgs.rasterize(**gaussians, **camera, t=0.5)
    bad = dict(gaussians, opacities=gaussians["opacities"].clone())
    bad["opacities"][7] = 1.5
    _, _, _, counts = render.render_frame(**bad, **camera, t=0.5, defer=True)
    with pytest.raises(RenderError, match="opacities must lie in"):
        counts.read()


def sequence_setup(device: str, frames: int = 12):
    scene, gaussians, _ = scene_on(device, seed=9, n=500)
    g = torch.Generator().manual_seed(2)
    n = gaussians["means"].shape[0]
    gaussians["t_means"] = torch.rand(n, generator=g).to(device)
    gaussians["t_scales"] = (10.0 ** (-2 + 2 * torch.rand(n, generator=g))).to(device)
    poses = np.repeat(np.linalg.inv(scene["viewmat"].numpy())[None], frames, 0)
    poses[:, 0, 3] += np.linspace(0.0, 0.4, frames)  # a camera that moves: the totals change
    return gaussians, Cameras.create(poses, scene["K"].numpy(), 45, 37)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("to_cpu", [True, False])
def test_pipelined_sequences_yield_what_waiting_ones_do(device, to_cpu, fresh_bounds):
    """Every frame equal to rasterize's, in order, with its counts; the callable form too (the same
    cloud, or new tensors for every frame, let go while the frame may still read them), and a sequence
    whose bound is too small for its frames (each is rendered again before it is yielded)."""
    gaussians, cams = sequence_setup(device)
    order = [3, 0, 7, 11, 5, 6, 1]
    want = {}
    for k in order:
        image, _, meta = tomgs.rasterize(**gaussians, viewmat=cams.viewmats(device)[k], K=cams.Ks(device)[k],
                                         width=45, height=37, t=float(cams.times[k]))
        want[k] = (image.clamp(0, 1), meta["n_intersections"])
    calls = []

    def per_frame(k):
        calls.append(k)
        return gaussians

    def fresh_per_frame(k):  # new tensors every frame, released while the frame may still read them
        return {name: value.clone() for name, value in gaussians.items()}

    for source in (gaussians, per_frame, fresh_per_frame, "shrunk"):
        if source == "shrunk":
            assert min(want[k][1] for k in order[:2]) > 300  # the first two frames overflow a bound of 300
            for key in fresh_bounds._capacity:
                fresh_bounds._capacity[key] = 300
                fresh_bounds._recent[key].clear()
            source = gaussians
        got = [(k, image, meta) for k, image, meta in
               render_sequence(source, cams, order, device=device, to_cpu=to_cpu, pipelined=True)]
        assert [k for k, _, _ in got] == order
        for k, image, meta in got:
            assert image.device.type == ("cpu" if to_cpu else torch.device(device).type)
            assert torch.equal(image.to(device), want[k][0]), k
            assert meta["n_intersections"] == want[k][1]
    assert calls == order


@pytest.mark.parametrize("device", DEVICES)
def test_a_pipelined_sequence_raises_before_yielding_a_bad_frame(device, fresh_bounds):
    gaussians, cams = sequence_setup(device, frames=4)
    bad = dict(gaussians, scales=gaussians["scales"].clone())
    bad["scales"][:, 0] = -1.0  # every Gaussian, so that those alive at any frame include some
    good_first = lambda k: gaussians if k == 0 else bad  # noqa: E731
    frames = render_sequence(good_first, cams, [0, 0, 1, 2], device=device, pipelined=True)
    assert next(frames)[0] == 0 and next(frames)[0] == 0
    with pytest.raises(RenderError, match="scales must be >= 0"):
        next(frames)


@pytest.mark.parametrize("sparse_adam", [False, True])
def test_training_steps_that_do_not_wait_train_what_waiting_ones_do(sparse_adam, fresh_bounds):
    """A pipelined Trainer (a GPU's default: frames that do not wait for their counts) trains bit for
    bit what one that waits trains, densification included; steps whose keys overflow the bound
    render again, and their first gradients are dropped. (Frames drawn uniformly: a pipelined
    sampler hears its PSNRs a flush later, which would pick other frames.)"""
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer

    images, cams, points, colors = synthetic_clip(3, 32, 18)
    models = {}
    for mode in ("wait", "defer", "overflow"):
        torch.manual_seed(0)
        trainer = Trainer(images, cams, points, colors, small_config(120, sparse_adam=sparse_adam,
                                                                      sampling="uniform"), CPU)
        trainer.pipelined = mode != "wait"
        renders = []
        render_once = trainer.render
        trainer.render = lambda *a, **kw: renders.append(kw.get("defer")) or render_once(*a, **kw)
        for step in range(120):
            if mode == "overflow" and step % 10 == 5:  # as if recent frames had been far smaller
                for key in fresh_bounds._capacity:
                    fresh_bounds._capacity[key] = 50
                    fresh_bounds._recent[key].clear()
            trainer.step()
        again = len(renders) - 120  # steps rendered twice: deferred, overflowed, then waiting
        assert again == (12 if mode == "overflow" else 0), mode
        assert renders.count(False) == (120 if mode == "wait" else again)  # the waiting mode counted the size
        models[mode] = {name: p.detach().clone() for name, p in trainer.model.parameters_by_name().items()}
    for mode in ("defer", "overflow"):
        for name, value in models["wait"].items():
            assert torch.equal(models[mode][name], value), (mode, name)


def test_a_pipelined_trainer_hands_its_psnrs_to_the_sampler_a_flush_late():
    """Every SAMPLER_LAG steps the PSNRs go to the host without waiting; the sampler hears them at the
    next flush. A checkpoint carries what it has not heard, and hands it nothing (that would change its
    next draws: a seeded run would not repeat)."""
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer
    from tomgs.train.trainer import SAMPLER_LAG

    images, cams, points, colors = synthetic_clip(3, 32, 18)
    heard = {}
    for pipelined in (False, True):
        torch.manual_seed(0)
        trainer = Trainer(images, cams, points, colors, small_config(100, sampling="uniform"), CPU)
        trainer.pipelined = pipelined
        measured = []
        updates = []
        update = trainer.sampler.update
        trainer.sampler.update = lambda k, value: updates.append((k, value)) or update(k, value)
        for step in range(2 * SAMPLER_LAG + 3):
            trainer.step()
            measured.append(len(updates))
        assert measured[SAMPLER_LAG - 1] == (SAMPLER_LAG if not pipelined else 0)
        assert measured[2 * SAMPLER_LAG - 1] == (2 * SAMPLER_LAG if not pipelined else SAMPLER_LAG)
        before = list(updates)
        pending = trainer.state_dict()["sampler"]["pending"]
        assert updates == before and len(updates) + len(pending) == 2 * SAMPLER_LAG + 3
        heard[pipelined] = updates + [tuple(p) for p in pending]
    assert heard[True] == heard[False]  # the same PSNRs, in the same order


def test_a_pipelined_trainer_resumes_with_its_flushes_on_the_same_steps(tmp_path):
    """A checkpoint written between flushes, the older PSNRs on their way to the sampler: resumed, they
    arrive at the step they would have, and the run goes on as if never stopped."""
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer
    from tomgs.train.trainer import SAMPLER_LAG

    images, cams, points, colors = synthetic_clip(3, 32, 18)

    def trainer():
        made = Trainer(images, cams, points, colors, small_config(100), CPU)
        made.pipelined = True
        return made

    straight, first = trainer(), trainer()
    for _ in range(2 * SAMPLER_LAG + 5):
        straight.step()
        first.step()
    state = first.state_dict()
    assert first._in_flight is not None and len(state["sampler"]["pending"]) == SAMPLER_LAG + 5
    resumed = trainer()
    resumed.load_checkpoint(state)
    for _ in range(2 * SAMPLER_LAG + 3):
        straight.step()
        resumed.step()
        assert torch.equal(straight.sampler.psnr, resumed.sampler.psnr)
    for name, value in straight.model.parameters_by_name().items():
        assert torch.equal(value, resumed.model.parameters_by_name()[name]), name


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_without_gaussians_does_not_wait_either(device, fresh_bounds):
    _, gaussians, camera = scene_on(device)
    tomgs.rasterize(**gaussians, **camera, t=0.5)  # the size is counted
    empty = {name: value[:0] for name, value in gaussians.items()}
    image, alpha, _, counts = render.render_frame(**empty, **camera, t=0.5, defer=True)
    assert counts is not None and counts.read() == dict(n_visible=0, n_alive=0, n_intersections=0)
    assert not counts.overflowed and not image.any() and not alpha.any()
