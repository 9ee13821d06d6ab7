"""The built-in XPBD soft body (tomgs.edit.physics) on tiny meshes, CPU: Warp CPU kernels run serially."""

from __future__ import annotations

import numpy as np
import pytest

from tomgs.edit import physics
from tomgs.edit.physics import SimConfig, box_tets, simulate, simulate_with_stats
from tomgs.io import InputError

FPS = 24.0


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """[..., T] signed volumes of tets over vertices [..., V, 3] (independent of the solver's code)."""
    x = vertices[..., tets, :]
    e1, e2, e3 = (x[..., k, :] - x[..., 0, :] for k in (1, 2, 3))
    return np.linalg.det(np.stack([e1, e2, e3], axis=-1)) / 6.0


def cube5() -> tuple[np.ndarray, np.ndarray]:
    """A unit cube in 5 tets (one central, four corners), each ordered to positive volume."""
    vertices = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float64)
    tets = np.array([[1, 2, 4, 7], [0, 1, 2, 4], [3, 1, 2, 7], [5, 1, 4, 7], [6, 2, 4, 7]])
    flip = signed_volumes(vertices, tets) < 0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return vertices, tets


def masses(vertices, tets) -> np.ndarray:
    m = np.zeros(len(vertices))
    np.add.at(m, tets.ravel(), np.repeat(signed_volumes(vertices, tets) / 4.0, 4))
    return m


def test_meshes_are_positive():
    for vertices, tets in (cube5(), box_tets((3, 3, 3))):
        assert (signed_volumes(vertices, tets) > 0).all()
    vertices, tets = box_tets((3, 3, 3), size=(2.0, 1.0, 1.0))
    assert signed_volumes(vertices, tets).sum() == pytest.approx(2.0)


def test_colouring_never_shares_a_vertex_within_a_colour():
    # on the CPU kernels run serially, so a race between constraints of one colour would go unseen
    vertices, tets = box_tets((3, 3, 3))
    edges, _ = physics._edges(tets)
    for items in (edges, tets):
        colours = physics._colour(items, len(vertices))
        for c in np.unique(colours):
            used = items[colours == c].ravel()
            assert len(np.unique(used)) == len(used)
        assert colours.max() < 32  # a few dozen launches per substep, not one per constraint


def test_drop_settles_on_the_floor_without_inverting():
    vertices, tets = box_tets((3, 3, 3))
    config = SimConfig.drop(physics.body_extent(vertices))
    result = simulate_with_stats(vertices, tets, config)
    frames = result.vertices
    assert frames.shape == (config.frames, len(vertices), 3) and np.isfinite(frames).all()
    volumes = signed_volumes(frames, tets)
    assert volumes.min() > 0 and result.inverted_frames == []
    assert 0.5 < result.min_volume_ratio < 0.999  # squeezed a little, never flat
    floor = vertices[:, 1].max()  # +y is down: the floor defaults to the lowest rest vertex
    lowest = frames[..., 1].max(axis=1)
    assert lowest[0] == pytest.approx(floor - 1.5)  # started raised by drop_height
    assert (lowest <= floor + 1e-4).all()  # never through the floor
    height = frames[..., 1].max(axis=1) - frames[..., 1].min(axis=1)
    assert height.min() < 0.9  # it is soft: the impact squashes it
    assert abs(lowest[-1] - floor) < 1e-3  # resting on the floor
    speed = np.linalg.norm(frames[-1] - frames[-2], axis=1).max() * FPS
    assert speed < 0.05 and result.at_rest and result.final_speed < 0.05


def test_spin_bounces_without_inverting():
    vertices, tets = box_tets((3, 3, 3))
    config = SimConfig.spin(physics.body_extent(vertices))
    result = simulate_with_stats(vertices, tets, config)
    frames = result.vertices
    assert np.isfinite(frames).all()
    assert signed_volumes(frames, tets).min() > 0 and result.inverted_frames == []
    floor = vertices[:, 1].max()
    assert (frames[..., 1].max(axis=1) <= floor + 1e-4).all()
    com_y = frames[..., 1].mean(axis=1)  # y down: smaller is higher
    touch = np.argmax(frames[..., 1].max(axis=1) > floor - 1e-3)
    deepest = touch + np.argmax(com_y[touch:touch + 12])  # the impact squeezes on after the touch
    assert com_y[deepest:].min() < com_y[deepest] - 0.1  # then the centre rises again: a bounce
    assert frames[-1, :, 0].mean() > frames[0, :, 0].mean() + 1.0  # thrown sideways
    # it turned: a body diagonal changed direction by well over 45 degrees at some point
    diagonal = frames[:, -1] - frames[:, 0]
    cosine = diagonal @ diagonal[0] / (np.linalg.norm(diagonal, axis=1) * np.linalg.norm(diagonal[0]))
    assert cosine.min() < 0.5


def test_fine_mesh_spin_keeps_every_tet_positive():
    # 12 cells a side: one pass per substep used to push the tets at the floor contact into the
    # floor, where collide_ground undid it, so the contact flattened them (min V/V0 -0.04 at frame 33)
    vertices, tets = box_tets((12, 12, 12))
    config = SimConfig.spin(physics.body_extent(vertices), frames=40)
    result = simulate_with_stats(vertices, tets, config)
    assert result.inverted_frames == [] and result.min_volume_ratio > 0.2
    assert (signed_volumes(result.vertices, tets) > 0).all()
    floor = vertices[:, 1].max()
    assert (result.vertices[..., 1] <= floor + 1e-4).all()


def test_frame_check_counts_inverted_tets():
    import warp as wp

    from tomgs.kernels import xpbd
    from tomgs.runtime import init_warp

    init_warp()
    vertices, tets = cube5()
    moved = vertices.copy()
    moved[0] = [0.9, 0.9, 0.9]  # through the central tet's face: the corner tet of vertex 0 turns inside out
    volumes = signed_volumes(moved, tets) / signed_volumes(vertices, tets)
    assert (volumes <= 0).sum() == 1
    frames = wp.zeros((2, 8), dtype=wp.vec3, device="cpu")
    ratio = wp.full(2, np.inf, dtype=float, device="cpu")
    inverted = wp.zeros(2, dtype=int, device="cpu")
    args = [wp.array(tets.astype(np.int32), dtype=wp.vec4i, device="cpu"),
            wp.array(signed_volumes(vertices, tets).astype(np.float32), dtype=float, device="cpu")]
    for f, x in enumerate((vertices, moved)):
        positions = wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu")
        wp.launch(xpbd.record_frame, dim=8, device="cpu", inputs=[positions, *args, f, frames, ratio, inverted])
    assert inverted.numpy().tolist() == [0, 1]
    np.testing.assert_allclose(ratio.numpy(), [1.0, volumes.min()], rtol=1e-5)
    np.testing.assert_allclose(frames.numpy()[1], moved, rtol=1e-6)


def test_left_alone_stays_exactly_at_rest():
    vertices, tets = box_tets((2, 2, 2), size=(1.0, 0.5, 2.0), origin=(3.0, -1.0, 5.0))
    config = SimConfig(frames=12, gravity=(0.0, 0.0, 0.0), floor=False)
    frames = simulate(vertices, tets, config)
    assert frames.shape == (12, len(vertices), 3)
    np.testing.assert_allclose(frames[0], vertices, atol=1e-6)
    assert (frames == frames[0]).all()


def test_rigid_throw_follows_the_ballistic_parabola():
    vertices, tets = cube5()
    v0, spin, g = np.array([1.0, -3.0, 0.5]), 4.0, np.array([0.0, 9.81, 0.0])
    config = SimConfig(frames=25, fps=FPS, gravity=tuple(g), floor=False, edge_compliance=0.0,
                       volume_compliance=0.0, initial_velocity=tuple(v0), initial_spin=(0.0, 0.0, spin))
    frames = simulate(vertices, tets, config)
    m = masses(vertices, tets)
    com = (m @ frames) / m.sum()  # [F, 3]
    t = np.arange(config.frames) / FPS
    expected = com[0] + t[:, None] * v0 + 0.5 * t[:, None] ** 2 * g
    h = 1.0 / (FPS * config.substeps)
    assert np.abs(com - expected).max() < 9.81 * h * t[-1]  # semi-implicit Euler is off by g h t / 2
    # rigid: edge lengths kept; spinning at `spin` rad/s about z
    edges, _ = physics._edges(tets)
    lengths = np.linalg.norm(frames[:, edges[:, 0]] - frames[:, edges[:, 1]], axis=-1)
    np.testing.assert_allclose(lengths, np.broadcast_to(lengths[0], lengths.shape), rtol=2e-3)
    d = frames[:, 1, :2] - frames[:, 0, :2]  # an edge along x: its angle in the xy plane
    angle = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    np.testing.assert_allclose(angle - angle[0], spin * t, atol=0.02 * spin * t[-1])


def test_friction_stops_a_slide():
    vertices, tets = cube5()

    def slide(friction: float) -> np.ndarray:
        config = SimConfig(frames=24, edge_compliance=0.0, friction=friction, initial_velocity=(2.0, 0.0, 0.0))
        return simulate(vertices, tets, config)[..., 0].mean(axis=1) - 0.5  # centre's travel along x

    t = np.arange(24) / FPS
    # no friction: slides on (to float32 rounding: ~1e-3 after 2 body lengths)
    np.testing.assert_allclose(slide(0.0), 2.0 * t, atol=2e-3)
    stop = 2.0**2 / (2 * 0.5 * 9.81)  # Coulomb: v^2 / (2 mu g)
    travel = slide(0.5)
    # within 15%: the floor's normal push is summed from constraints solved with the held vertex fixed,
    # which overstates it a little (the stop comes ~12% short)
    assert abs(travel[-1] - stop) < 0.15 * stop and travel[-1] == pytest.approx(travel[-2], abs=1e-4)


def test_stiffer_material_compresses_less():
    vertices, tets = box_tets((2, 2, 2))

    def squash(compliance: float) -> float:
        frames = simulate(vertices, tets, SimConfig.drop(frames=30, edge_compliance=compliance))
        return (frames[..., 1].max(axis=1) - frames[..., 1].min(axis=1)).min()

    soft, stiff = squash(1e-2), squash(1e-3)
    assert stiff > soft + 0.05 and soft < 0.95


def test_scene_scale_does_not_change_the_motion():
    # the solver works in units of the body's extent; the presets scale gravity and drop height
    vertices, tets = box_tets((2, 2, 2))
    small = simulate(vertices, tets, SimConfig.spin(1.0, frames=30))
    moved = vertices * 7.0 + np.array([1.0, -2.0, 3.0])
    large = simulate(moved, tets, SimConfig.spin(physics.body_extent(moved), frames=30))
    np.testing.assert_allclose(large, small * 7.0 + np.array([1.0, -2.0, 3.0]), atol=1e-3 * 7.0)


def test_inverted_rest_tet_is_an_input_error():
    vertices, tets = box_tets((1, 1, 1))
    tets[3] = tets[3][[1, 0, 2, 3]]
    with pytest.raises(InputError, match=r"tet 3 .*inverted.*swap two of its vertices"):
        simulate(vertices, tets, SimConfig(frames=2))


def test_zero_volume_tet_is_an_input_error():
    vertices, tets = cube5()
    vertices = np.vstack([vertices, [[0.5, 0.5, 0.0]]])  # in the plane of vertices 0, 1, 2
    tets = np.vstack([tets, [[0, 1, 2, 8]]])
    with pytest.raises(InputError, match=r"tet 5 .*no volume"):
        simulate(vertices, tets, SimConfig(frames=2))


@pytest.mark.parametrize("change, words", [
    ({"restitution": 2.0}, "restitution"),
    ({"substeps": 0}, "substeps"),
    ({"gravity": (0.0, float("nan"), 0.0)}, "gravity"),
    ({"edge_compliance": -1.0}, "edge_compliance"),
])
def test_bad_settings_are_input_errors(change, words):
    vertices, tets = cube5()
    with pytest.raises(InputError, match=words):
        simulate(vertices, tets, SimConfig(frames=2, **change))


def test_bad_mesh_arrays_are_input_errors():
    vertices, tets = cube5()
    with pytest.raises(InputError, match="outside"):
        simulate(vertices, tets + 1, SimConfig(frames=2))
    with pytest.raises(InputError, match=r"\[V,3\]"):
        simulate(vertices[:, :2], tets, SimConfig(frames=2))
    with pytest.raises(InputError, match="not finite"):
        simulate(np.where(vertices == 1.0, np.inf, vertices), tets, SimConfig(frames=2))


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_matches_the_cpu_and_repeats_exactly():
    """The GPU path (one CUDA graph per frame's substeps) follows the CPU run and repeats bit for bit."""
    vertices, tets = box_tets((3, 3, 3))
    config = SimConfig.spin(physics.body_extent(vertices), frames=24)
    cpu = simulate(vertices, tets, config, device="cpu")
    gpu = simulate(vertices, tets, config, device="cuda")
    again = simulate(vertices, tets, config, device="cuda")
    assert np.array_equal(gpu, again)
    # float32 on both, different instruction order: allow drift well under a hundredth of the body
    assert np.abs(gpu - cpu).max() < 1e-2 * physics.body_extent(vertices)
    assert (signed_volumes(gpu, tets) > 0).all()
