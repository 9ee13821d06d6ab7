"""Built-in soft-body physics: XPBD on a tetrahedral mesh (tomgs.kernels.xpbd), no Blender needed.

    simulate(rest_vertices [V,3], tets [T,4], SimConfig, device) -> vertices [F,V,3] per frame

World axes are OpenCV (x right, y down, z forward), so gravity defaults to +y. Frame 0 is the start
pose (the rest pose raised by `drop_height`); frame f is the state at time f / fps.

Units. The solver works in units of the body's extent L (the longest side of the rest mesh's
bounding box), centred on the mesh: positions, velocities, gravity, drop height and the floor are
divided by L on the way in and multiplied back on the way out. The compliances and the damping are
therefore scale-free: the same values give the same wobble for a body of any size. Gravity,
velocities and drop height are in scene units; the presets `SimConfig.drop(extent)` and
`SimConfig.spin(extent)` scale them by the body's extent (`body_extent(rest_vertices)`) so that a
body of any size falls like a 1 m object under Earth gravity, which is what looks right in a
monocular scene whose scale is arbitrary.

Material. Mass is the rest volume (density 1) lumped a quarter to each vertex of each tet. Each
edge keeps its rest length and each tet its rest volume, as strain constraints C = l/l0 - 1 and
C = V/V0 - 1 with compliance `edge_compliance` / `volume_compliance` divided by the element's share
of the volume (so refining the mesh keeps the material). 0 is rigid; ~1e-3 is a stiff jelly,
~1e-2 a soft one. Volume compliance 0 keeps the body incompressible, which is also what keeps the
tets from inverting.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from tomgs.errors import InputError
from tomgs.geometry import signed_volumes
from tomgs.kernels import xpbd
from tomgs.runtime import init_warp

# A tet flatter than this (volume over its longest edge cubed; a regular tet has 0.118) is degenerate.
MIN_TET_SHAPE = 1e-9
# Final vertex speed, in body extents per second, below which the body counts as at rest.
REST_SPEED = 0.05
EARTH_GRAVITY = 9.81


@dataclass
class SimConfig:
    """Settings of one simulation; see the module docstring for units.

    frames: frames written (frame 0 = start pose); fps: frames per second of the scene;
    substeps: solver steps per frame; iterations: constraint passes per substep;
    gravity: acceleration, scene units / s^2, world (OpenCV) axes;
    floor: False for no floor; floor_point: a point on the floor (None: the lowest rest vertex
    along gravity); floor_normal: pointing up (None: against gravity);
    edge_compliance, volume_compliance: inverse stiffness (scale-free, 0 = rigid);
    damping: velocity damping rate (air drag), 1/s; viscosity: material damping, the relaxation
    time of the strain in seconds (damps wobble, not falling or spinning); friction: Coulomb
    coefficient at the floor; restitution: 0..1, the share of a vertex's approach speed it keeps
    when it hits the floor (per vertex: the impulse does not reach the rest of the body within the
    substep, so a body's bounce comes mostly from its elasticity, the compliances and viscosity);
    initial_velocity: scene units / s; initial_spin: rad/s about the centre of mass (axis =
    direction, world axes); drop_height: start raised this far against gravity, scene units.
    """

    frames: int = 80
    fps: float = 24.0
    substeps: int = 20
    iterations: int = 1
    gravity: tuple = (0.0, EARTH_GRAVITY, 0.0)
    floor: bool = True
    floor_point: tuple | None = None
    floor_normal: tuple | None = None
    edge_compliance: float = 1e-3
    volume_compliance: float = 0.0
    damping: float = 0.0
    viscosity: float = 0.02
    friction: float = 0.5
    restitution: float = 0.2
    initial_velocity: tuple = (0.0, 0.0, 0.0)
    initial_spin: tuple = (0.0, 0.0, 0.0)
    drop_height: float = 0.0

    @classmethod
    def drop(cls, extent: float = 1.0, **changes) -> SimConfig:
        """The paper's 'soft body dropped on a surface': a soft body falls 1.5 body sizes, squashes
        and settles. `extent` = body_extent(rest_vertices); `changes` override any field."""
        base = cls(gravity=(0.0, EARTH_GRAVITY * extent, 0.0), drop_height=1.5 * extent,
                   edge_compliance=1e-2, volume_compliance=0.0, viscosity=0.1, damping=0.5, friction=0.8,
                   restitution=0.1)
        return dataclasses.replace(base, **changes)

    @classmethod
    def spin(cls, extent: float = 1.0, **changes) -> SimConfig:
        """The paper's 'spinning body bouncing': a stiffer body thrown sideways and up while
        spinning, bouncing on the floor before it settles."""
        base = cls(gravity=(0.0, EARTH_GRAVITY * extent, 0.0), drop_height=1.0 * extent,
                   initial_velocity=(1.5 * extent, -2.0 * extent, 0.0), initial_spin=(0.0, 0.0, 6.0),
                   edge_compliance=2e-3, volume_compliance=0.0, viscosity=0.02, friction=0.5, restitution=0.5)
        return dataclasses.replace(base, **changes)


@dataclass
class SimResult:
    """A simulation and what to trust about it.

    vertices [F,V,3] float64 world axes; min_volume_ratio: smallest V/V0 of any tet over all frames
    (<= 0 means a tet inverted); inverted_frames: frames with an inverted tet; final_speed: largest
    vertex speed at the end, scene units / s; at_rest: final_speed below REST_SPEED body extents / s.
    """

    vertices: np.ndarray
    min_volume_ratio: float
    inverted_frames: list
    final_speed: float
    at_rest: bool


def body_extent(rest_vertices) -> float:
    """Longest side of the bounding box of `rest_vertices` [V,3]: the unit the solver works in."""
    v = np.asarray(rest_vertices, dtype=np.float64)
    return float((v.max(axis=0) - v.min(axis=0)).max())


def simulate(rest_vertices, tets, config: SimConfig, device: str = "cpu") -> np.ndarray:
    """Vertices [F,V,3] float64 of the body per frame; see `simulate_with_stats` for the checks."""
    return simulate_with_stats(rest_vertices, tets, config, device).vertices


def simulate_with_stats(rest_vertices, tets, config: SimConfig, device: str = "cpu") -> SimResult:
    """Run the simulation: rest_vertices [V,3], tets [T,4] int (positive volume), on a Warp
    device ("cpu", "cuda", "cuda:N"). Raises InputError for bad input and if the motion blows up."""
    rest, tets = _check_mesh(rest_vertices, tets)
    _check_config(config)
    extent = body_extent(rest)
    centre = 0.5 * (rest.max(axis=0) + rest.min(axis=0))
    rest_n = (rest - centre) / extent  # body units, centred: the solver's frame
    volumes = signed_volumes(rest_n, tets)

    # mass lumped from tets (density 1); an unused vertex keeps inverse mass 0 (no constraint moves it)
    mass = np.zeros(len(rest))
    np.add.at(mass, tets.ravel(), np.repeat(volumes / 4.0, 4))
    inv_mass = np.divide(1.0, mass, out=np.zeros_like(mass), where=mass > 0)

    gravity = np.asarray(config.gravity, dtype=np.float64) / extent
    up = _floor_normal(config, gravity)
    start = rest_n + up * (config.drop_height / extent)
    com = (mass @ start) / mass.sum()
    velocity = np.asarray(config.initial_velocity, dtype=np.float64) / extent
    velocity = velocity + np.cross(np.asarray(config.initial_spin, dtype=np.float64), start - com)
    if config.floor_point is None:
        floor_point = rest_n[np.argmin(rest_n @ up)]
    else:
        floor_point = (np.asarray(config.floor_point, dtype=np.float64) - centre) / extent

    init_warp()
    with wp.ScopedDevice(device):
        solver = _Solver(rest_n, start, velocity, inv_mass, tets, volumes, config, gravity, floor_point, up)
        frames, min_ratio, inverted, speed = solver.run(config.frames)

    vertices = frames.astype(np.float64) * extent + centre
    finite = np.isfinite(vertices).all(axis=(1, 2))
    if not finite.all():
        raise InputError(f"the simulation blew up at frame {int(np.argmin(finite))}: use more substeps, a larger "
                         "compliance or smaller velocities")
    return SimResult(vertices=vertices, min_volume_ratio=float(min_ratio.min()),
                     inverted_frames=[int(f) for f in np.flatnonzero(inverted)],
                     final_speed=speed * extent, at_rest=bool(speed < REST_SPEED))


class _Solver:
    """Device buffers and the recorded launches of one frame; body units, float32.

    rest, start [V,3]; velocity [V,3]; inv_mass [V]; tets [T,4]; volumes [T] rest volumes.
    """

    def __init__(self, rest, start, velocity, inv_mass, tets, volumes, config, gravity, floor_point, up):
        f32 = np.float32
        h = 1.0 / (config.fps * config.substeps)
        edges, edge_tet = _edges(tets)
        # per-constraint compliance: over the element's share of the volume (a tet gives a sixth to
        # each of its edges) and over h^2 (XPBD's alpha tilde)
        edge_volume = np.bincount(edge_tet, weights=np.repeat(volumes / 6.0, 6), minlength=len(edges))
        edge_colour, tet_colour = _colour(edges, len(rest)), _colour(tets, len(rest))
        edge_order, tet_order = np.argsort(edge_colour, kind="stable"), np.argsort(tet_colour, kind="stable")
        edges, edge_volume = edges[edge_order], edge_volume[edge_order]
        tets, volumes = tets[tet_order], volumes[tet_order]

        n = len(rest)
        self.x = wp.array(rest.astype(f32), dtype=wp.vec3)
        self.edges = wp.array(edges.astype(np.int32), dtype=wp.vec2i)
        self.tets = wp.array(tets.astype(np.int32), dtype=wp.vec4i)
        self.rest_length = wp.zeros(len(edges), dtype=float)
        self.rest_volume = wp.zeros(len(tets), dtype=float)
        wp.launch(xpbd.rest_measures, dim=max(len(edges), len(tets)),
                  inputs=[self.x, self.edges, self.tets, self.rest_length, self.rest_volume])
        self.x.assign(start.astype(f32))
        self.v = wp.array(velocity.astype(f32), dtype=wp.vec3)
        self.x_prev = wp.zeros(n, dtype=wp.vec3)
        self.contact = wp.zeros(n, dtype=int)
        self.pushed = wp.zeros(n, dtype=float)
        self.lift = wp.zeros(n, dtype=wp.vec2)
        w = wp.array(inv_mass.astype(f32), dtype=float)
        self.lams = [wp.zeros(len(edges), dtype=float), wp.zeros(len(tets), dtype=float)]
        edge_alpha = wp.array((config.edge_compliance / (edge_volume * h * h)).astype(f32), dtype=float)
        tet_alpha = wp.array((config.volume_compliance / (volumes * h * h)).astype(f32), dtype=float)
        self.config = config

        def record(kernel, dim, *args):
            return wp.launch(kernel, dim=dim, inputs=list(args), record_cmd=True)

        up32 = wp.vec3(*up.astype(f32))
        self.predict = record(xpbd.predict, n, self.x, self.v, self.x_prev, self.contact, self.pushed,
                              self.lift, wp.vec3(*gravity.astype(f32)), h, math.exp(-config.damping * h))
        self.solve = []
        if config.floor:  # first the floor, so that the constraints know which vertices it holds
            self.solve.append(record(xpbd.touch_ground, n, self.x, self.contact, self.pushed,
                                     wp.vec3(*floor_point.astype(f32)), up32))
        for colours, kernel, items, rest_measure, alpha, lam, compliance in (
                (edge_colour, xpbd.solve_edges, self.edges, self.rest_length, edge_alpha, self.lams[0],
                 config.edge_compliance),
                (tet_colour, xpbd.solve_tets, self.tets, self.rest_volume, tet_alpha, self.lams[1],
                 config.volume_compliance)):
            # a rigid constraint is not a spring: damping it would only slow its projection
            gamma = config.viscosity / h if compliance > 0 else 0.0
            offsets = np.concatenate([[0], np.cumsum(np.bincount(colours))])
            for first, end in zip(offsets[:-1], offsets[1:]):
                self.solve.append(record(kernel, int(end - first), self.x, w, items, rest_measure, alpha, lam,
                                         self.x_prev, self.contact, self.lift, up32, gamma,
                                         int(first)))
        if config.floor:
            self.solve.append(record(xpbd.collide_ground, n, self.x, self.x_prev, self.contact, self.pushed,
                                     self.lift, wp.vec3(*floor_point.astype(f32)), up32, float(config.friction)))
        rest_speed = 2.0 * float(np.linalg.norm(gravity)) * h  # Mueller et al. 2020: slower contacts do not bounce
        self.update = record(xpbd.update_velocity, n, self.x, self.x_prev, self.v, self.contact, up32, 1.0 / h,
                             float(config.restitution), rest_speed)

    def step_frame(self) -> None:
        for _ in range(self.config.substeps):
            self.predict.launch()
            for lam in self.lams:
                lam.zero_()
            for _ in range(self.config.iterations):
                for cmd in self.solve:
                    cmd.launch()
            self.update.launch()

    def run(self, count: int):
        """Frames [count,V,3] float32, min V/V0 [count], inverted tets [count], final max speed."""
        n, t = self.x.shape[0], self.tets.shape[0]
        frames = wp.zeros((count, n), dtype=wp.vec3)
        min_ratio = wp.full(count, math.inf, dtype=float)
        inverted = wp.zeros(count, dtype=int)
        graph = None
        if self.x.device.is_cuda:  # one CUDA graph per frame: thousands of tiny launches cost one
            with wp.ScopedCapture() as capture:
                self.step_frame()
            graph = capture.graph
        for f in range(count):
            if f:
                if graph is None:
                    self.step_frame()
                else:
                    wp.capture_launch(graph)
            wp.launch(xpbd.record_frame, dim=max(n, t),
                      inputs=[self.x, self.tets, self.rest_volume, f, frames, min_ratio, inverted])
        speed = float(np.linalg.norm(self.v.numpy(), axis=1).max())
        return frames.numpy(), min_ratio.numpy(), inverted.numpy(), speed


def _check_mesh(rest_vertices, tets) -> tuple[np.ndarray, np.ndarray]:
    rest = np.asarray(rest_vertices, dtype=np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3 or len(rest) < 4:
        raise InputError(f"rest vertices must be an array [V,3] with V >= 4, got shape {rest.shape}")
    if not np.isfinite(rest).all():
        raise InputError(f"rest vertex {int(np.argmin(np.isfinite(rest).all(axis=1)))} is not finite (NaN or inf)")
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0 or not np.issubdtype(tets.dtype, np.integer):
        raise InputError(f"tets must be an integer array [T,4] with T >= 1, got {tets.dtype} {tets.shape}")
    if tets.min() < 0 or tets.max() >= len(rest):
        raise InputError(f"tet {int(np.argmax((tets < 0).any(axis=1) | (tets >= len(rest)).any(axis=1)))} names a "
                         f"vertex outside 0..{len(rest) - 1}")
    tets = tets.astype(np.int64)
    if (np.sort(tets, axis=1)[:, 1:] == np.sort(tets, axis=1)[:, :-1]).any():
        bad = int(np.argmax((np.sort(tets, axis=1)[:, 1:] == np.sort(tets, axis=1)[:, :-1]).any(axis=1)))
        raise InputError(f"tet {bad} uses a vertex twice ({tets[bad].tolist()}): remove it")
    volumes = signed_volumes(rest, tets)
    corners = rest[tets]
    longest = np.max([np.linalg.norm(corners[:, a] - corners[:, b], axis=1)
                      for a in range(4) for b in range(a + 1, 4)], axis=0)
    shape = volumes / longest**3
    if (shape <= -MIN_TET_SHAPE).any():
        bad = int(np.argmax(shape <= -MIN_TET_SHAPE))
        raise InputError(f"tet {bad} ({tets[bad].tolist()}) is inverted in the rest pose (volume {volumes[bad]:.3g}): "
                         "swap two of its vertices so that its volume is positive")
    if (shape < MIN_TET_SHAPE).any():
        bad = int(np.argmax(shape < MIN_TET_SHAPE))
        raise InputError(f"tet {bad} ({tets[bad].tolist()}) has no volume in the rest pose (volume {volumes[bad]:.3g}, "
                         "its vertices lie in a plane): thicken it or remove it")
    return rest, tets


def _check_config(config: SimConfig) -> None:
    def need(ok: bool, what: str) -> None:
        if not ok:
            raise InputError(f"simulation setting {what}")

    need(int(config.frames) >= 1, f"frames must be >= 1, got {config.frames}")
    need(math.isfinite(config.fps) and config.fps > 0, f"fps must be > 0, got {config.fps}")
    need(int(config.substeps) >= 1, f"substeps must be >= 1, got {config.substeps}")
    need(int(config.iterations) >= 1, f"iterations must be >= 1, got {config.iterations}")
    for name in ("gravity", "initial_velocity", "initial_spin", "floor_point", "floor_normal"):
        value = getattr(config, name)
        if value is not None:
            need(np.shape(value) == (3,) and np.isfinite(np.asarray(value, dtype=np.float64)).all(),
                 f"{name} must be 3 finite numbers (x, y, z), got {value!r}")
    for name in ("edge_compliance", "volume_compliance", "damping", "viscosity", "friction"):
        value = getattr(config, name)
        need(math.isfinite(value) and value >= 0, f"{name} must be >= 0, got {value}")
    need(0 <= config.restitution <= 1, f"restitution must be in [0, 1], got {config.restitution}")
    need(math.isfinite(config.drop_height), f"drop_height must be finite, got {config.drop_height}")


def _floor_normal(config: SimConfig, gravity: np.ndarray) -> np.ndarray:
    """Unit 'up' [3]: the floor normal, also the direction `drop_height` raises the body."""
    up = -gravity if config.floor_normal is None else np.asarray(config.floor_normal, dtype=np.float64)
    length = np.linalg.norm(up)
    if length == 0:
        if config.floor or config.drop_height:
            raise InputError("simulation setting floor_normal is needed when gravity is zero (or set floor=False "
                             "and drop_height=0)")
        return np.array([0.0, -1.0, 0.0])  # unused: no floor, no drop
    return up / length


_TET_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])


def _edges(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges [E,2] of tets [T,4], and for each of the 6T tet edges its row in them [6T]."""
    pairs = np.sort(tets[:, _TET_EDGES].reshape(-1, 2), axis=1)
    edges, index = np.unique(pairs, axis=0, return_inverse=True)
    return edges, index.ravel()


def _colour(items: np.ndarray, n_vertices: int) -> np.ndarray:
    """Greedy colouring [K] of constraints items [K,k] (vertex indices): no two constraints of a
    colour share a vertex, so a colour can be solved in parallel without races."""
    used = [0] * n_vertices  # bit c set: the vertex is in a constraint of colour c
    colours = np.empty(len(items), dtype=np.int64)
    for k, row in enumerate(items.tolist()):
        taken = 0
        for i in row:
            taken |= used[i]
        c = (~taken & (taken + 1)).bit_length() - 1  # lowest free colour
        colours[k] = c
        for i in row:
            used[i] |= 1 << c
    return colours


def box_tets(cells=(1, 1, 1), size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A box of cells[0] x cells[1] x cells[2] cubes, 6 positive tets each (Kuhn split along the
    main diagonal, conforming across cells): vertices [V,3] float64, tets [T,4] int64."""
    nx, ny, nz = (int(c) for c in cells)
    grid = np.stack(np.meshgrid(*(np.linspace(0.0, s, c + 1) for s, c in zip(size, (nx, ny, nz))), indexing="ij"),
                    axis=-1)
    vertices = grid.reshape(-1, 3) + np.asarray(origin, dtype=np.float64)
    index = np.arange(len(vertices)).reshape(nx + 1, ny + 1, nz + 1)
    corner = index[:-1, :-1, :-1].ravel()
    step = np.array([(ny + 1) * (nz + 1), nz + 1, 1])  # index offset of +1 along x, y, z
    tets = []
    for axes in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [np.zeros(3, dtype=int)]
        for a in axes:  # walk 0 -> (1,1,1) one axis at a time: the 6 paths are the 6 tets
            path.append(path[-1] + np.eye(3, dtype=int)[a])
        tets.append(np.stack([corner + p @ step for p in path], axis=1))
    tets = np.concatenate(tets)
    flip = signed_volumes(vertices, tets) < 0  # half the paths are left-handed
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return vertices, tets
