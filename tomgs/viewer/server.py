"""`tomgs view`: a scene in the browser, its time scrubbed, seen from the clip's camera or from anywhere.

Built on viser (the optional extra `[view]`: its web client ships in the wheel, nothing is downloaded
at run time). The path is client-side splatting: for frame k the server sends the Gaussians alive at
the frame's time with their opacity at that time baked in (`tomgs.temporal.frozen_at`), as centres,
covariances (`tomgs.geometry.covariances`), RGB (`tomgs.render.sh`, seen from the clip's camera at frame k)
and opacities, and the browser sorts and draws them (viser's WebGL splats). Why this path: it needs
no GPU on the server, so the viewer runs on a CPU-only machine; the orbit camera moves at the
browser's frame rate with no round trip to the server; and a frame costs the server only its alive
subset, which `--device cuda` builds on the GPU. What the browser draws differs from `tomgs render`
in small ways (docs/viewer.md): covariances travel as float16 and colours as 8 bits, splats fainter
than 1% are skipped, and alpha is not clamped at 0.99.

Layers (`--layer fg.ply`, `tomgs render`'s compositing) have their own cameras. Frame k of a layer is
moved into the base scene's world by the affine map that the base camera k sees as the layer's own
camera k sees it: into the layer camera's axes, K_base^-1 K_layer (the same pixels under the base's
intrinsics; identity when both have the same K), scaled by s about the camera centre (a camera sees
the same image of a cloud scaled about its own centre), then out through the base camera. s puts the
layer in front of everything before it, as compositing does, and is chosen per frame
(`tomgs.render.layers.place_layer`, which `tomgs export --layer` uses too).

Selections are `tomgs edit --select` texts (tomgs.edit.selection): the viewer writes the text of the
box or sphere placed in it and selects with that text, so the viewer and the command line agree.
"""

from __future__ import annotations

import contextlib
import io
import math
import shlex
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.errors import InputError
from tomgs.geometry import covariances, rotmat_to_quat
from tomgs.render.layers import NEAR, place_layer
from tomgs.render.sh import sh_to_colors
from tomgs.temporal import frozen_at

INSTALL_HINT = 'pip install "tomgs[view]"'
FAR = 1e4  # viser's far plane (its default, 1000, would cut large scenes); its near plane is the rasterizer's
SELECTION_COLOR = (255, 0, 255)


def require_viser():
    """The viser module; InputError saying how to install it when it is missing."""
    try:
        import viser
    except ImportError:
        raise InputError(f"tomgs view needs viser, an optional extra: {INSTALL_HINT}") from None
    return viser


# ---- what one frame sends -------------------------------------------------------------------------

@dataclass
class Splats:
    """One scene's Gaussians at one frame as the browser draws them, in the base scene's world axes."""

    centers: np.ndarray  # float32 [M,3]
    covariances: np.ndarray  # float32 [M,3,3]
    rgbs: np.ndarray  # float32 [M,3] in [0, 1]
    opacities: np.ndarray  # float32 [M,1]: o(t) at the frame's time
    indices: np.ndarray  # int64 [M]: the Gaussians' indices in their scene

    def __len__(self) -> int:
        return len(self.centers)

    def unit(self) -> float:
        """A length near the median Gaussian's size: viser stores covariances as float16, so they travel
        divided by its square (and the node scaled by it) to stay far from float16's underflow; larger
        where the biggest Gaussian would overflow float16 (a fitted background's are thousands of
        times the median: on camel, inf covariances drew nothing)."""
        if not len(self):
            return 1.0
        size = float(np.median(np.sqrt(np.trace(self.covariances, axis1=1, axis2=2) / 3.0)))
        largest = float(np.abs(self.covariances).max())
        if math.isfinite(largest):
            size = max(size, math.sqrt(largest / FLOAT16_ROOM))
        return size if math.isfinite(size) and size > 0 else 1.0


FLOAT16_ROOM = 3e4  # the largest covariance entry sent: half of float16's largest finite value (65504)


def clip_camera(cameras: Cameras, k: int) -> dict:
    """The clip's camera at position k as viser takes a camera: position, look_at (one unit ahead), up
    (OpenCV: -y of the camera) and vertical field of view in radians."""
    c2w = cameras.c2w[k]
    axes = c2w[:3, :3] / np.linalg.norm(c2w[:3, :3], axis=0)
    position = c2w[:3, 3]
    return dict(position=position, look_at=position + axes[:, 2], up=-axes[:, 1],
                fov=2.0 * math.atan(cameras.height / (2.0 * cameras.K[1, 1])))


class ViewScene:
    """A scene and its layers as the viewer shows them: per position k, one `Splats` per scene, the
    base's first, each layer in front of what comes before it (the last in front, as `tomgs render`)."""

    def __init__(self, scene, layers=(), device="cpu"):
        self.scene, self.layers = scene, list(layers)
        self.cameras: Cameras = scene.cameras
        self.device = torch.device(device)
        self._inputs = [self._prepare(s.model) for s in [scene, *self.layers]]
        self._viewmats = [s.cameras.viewmats(self.device) for s in [scene, *self.layers]]

    def _prepare(self, model) -> dict:
        """The rasterizer's inputs on the device, with what does not change over time computed once
        (covariances, row indices); `frozen_at` keeps the alive rows of every key."""
        with torch.no_grad():
            g = {name: value.detach().to(self.device) for name, value in model.render_inputs().items()}
            g["covariances"] = covariances(g["quats"], g["scales"])
            g["index"] = torch.arange(len(model), device=self.device)
        return g

    def position_of(self, frame_number: int) -> int:
        """The position of the scene frame whose number is nearest `frame_number`."""
        return int(np.argmin(np.abs(self.cameras.frame_indices - int(frame_number))))

    @torch.no_grad()
    def _alive(self, i: int, k: int) -> dict:
        """Scene i's Gaussians alive at position k: means, covariances, colour seen from its camera k,
        baked opacities and indices, on the device."""
        g = frozen_at(self._inputs[i], float(self.cameras.times[k]))
        rgbs = sh_to_colors(g["colors"], g["means"], self._viewmats[i][k]).clamp(0.0, 1.0)
        return dict(means=g["means"], covariances=g["covariances"], rgbs=rgbs, opacities=g["opacities"],
                    index=g["index"])

    @torch.no_grad()
    def frame(self, k: int) -> list[Splats]:
        """The splats of position k: the base's, then each layer's placed in the base's world in front of
        what comes before it (tomgs.render.layers.place_layer)."""
        out = [_splats(self._alive(0, k))]
        for i, layer in enumerate(self.layers, start=1):
            g = self._alive(i, k)
            behind = np.concatenate([splats.centers for splats in out])
            matrix, keep = place_layer(self.cameras, layer.cameras, k, behind, g["means"].cpu().numpy())
            g = {name: value[torch.as_tensor(keep, device=self.device)] for name, value in g.items()}
            m = torch.as_tensor(matrix, dtype=g["means"].dtype, device=self.device)
            g["means"] = g["means"] @ m[:3, :3].T + m[:3, 3]
            g["covariances"] = m[:3, :3] @ g["covariances"] @ m[:3, :3].T
            out.append(_splats(g))
        return out


def _splats(g: dict) -> Splats:
    def host(x, dtype=np.float32):
        return x.detach().cpu().numpy().astype(dtype, copy=False)

    return Splats(host(g["means"]), host(g["covariances"]), host(g["rgbs"]), host(g["opacities"])[:, None],
                  host(g["index"], np.int64))


# ---- selections ---------------------------------------------------------------------------------

SHAPES = ("box", "sphere")


def _number(value: float) -> str:
    return f"{float(value):.6g}"


def selector_text(shape: str, centre, size) -> str:
    """The `--select` text of a box (`size`: its sides x, y, z) or a sphere (`size`: its radius)
    about `centre`, in world axes; numbers to 6 significant digits."""
    centre = np.asarray(centre, dtype=np.float64)
    if shape == "box":
        half = np.abs(np.asarray(size, dtype=np.float64)) / 2.0
        numbers = [*(centre - half), *(centre + half)]
    elif shape == "sphere":
        numbers = [*centre, abs(float(size))]
    else:
        raise ValueError(f"shape must be one of {SHAPES}, got {shape!r}")
    return f"{shape}:" + ",".join(_number(v) for v in numbers)


def time_text(t: float) -> str:
    """The `--select` text of the Gaussians alive at clip time t."""
    return f"time:{_number(t)},{_number(t)}"


def select_with(model, cameras: Cameras, texts) -> np.ndarray:
    """Sorted indices that `tomgs edit --select TEXT ...` picks (tomgs.edit.selection); empty where
    the command would refuse a selection that matches nothing."""
    from tomgs.edit.selection import parse_selector, select

    selectors = [parse_selector(text) for text in texts]  # our own texts: a bad one is a bug, let it raise
    if any(s.kind not in (*SHAPES, "time") for s in selectors):
        raise ValueError("the viewer selects by box, sphere and time only")
    try:
        return select(model, cameras, selectors)
    except InputError:  # box, sphere and time raise only for an empty selection
        return np.zeros(0, dtype=np.int64)


def option_text(texts) -> str:
    return " ".join(f"--select {shlex.quote(text)}" for text in texts)


# ---- the server -----------------------------------------------------------------------------------

def _camera_known(client) -> bool:
    """Whether viser has this client's camera yet (its setters need it)."""
    try:
        return client.camera.update_timestamp != 0.0
    except AssertionError:
        return False


def _interrupt(signum, frame):
    raise KeyboardInterrupt


class Viewer:
    """A running viewer: a viser server showing `view` (a ViewScene), with a time slider, play and
    pause, the clip's camera or a free orbit camera, and a box or sphere selection. Messages (the
    selection texts) go to `echo`."""

    def __init__(self, view: ViewScene, scene_name: str, host: str = "127.0.0.1", port: int = 8080,
                 layer_names=(), echo=print):
        viser = require_viser()
        from tomgs.render.jobs import render_defaults

        self.view, self.scene_name, self.echo = view, scene_name, echo
        cams = view.cameras
        self.background, self.fps = render_defaults(view.scene.info)
        self._lock = threading.RLock()  # GUI callbacks run on viser's threads, playing on its own
        self._stopped = threading.Event()
        self._position = self._shown = None
        self._alive = np.zeros(0, dtype=np.int64)  # the base's Gaussians alive at the frame shown
        self._printed = None
        self._syncing = False  # set while the gizmo writes the centre field: not a user's edit
        self.host = host
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: the caller prints the URL
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.timings = {"first_payload": None, "payloads": []}  # what benchmarks/view_speed.py reports

        server = self.server
        server.scene.set_up_direction("-y")  # OpenCV axes: y down, as frame 0 of every scene
        server.gui.configure_theme(show_share_button=False)
        server.scene.set_background_image(np.full((4, 4, 3), np.array(self.background) * 255, np.uint8), "png")
        server.initial_camera.near, server.initial_camera.far = NEAR, FAR
        self._nodes = [server.scene.add_gaussian_splats(
            f"/scene/{j}", np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 1)))
            for j in range(1 + len(view.layers))]
        means = view.scene.model.means.detach().cpu().double().numpy()
        lo, hi = np.percentile(means, [10, 90], axis=0) if len(means) else (np.zeros(3), np.ones(3))
        self._middle, self._extent = (lo + hi) / 2.0, float(np.maximum(hi - lo, 1e-6).max())

        numbers = cams.frame_indices
        step = int(np.gcd.reduce(np.diff(numbers))) if len(numbers) > 1 else 1
        with server.gui.add_folder("Time"):
            self.slider = server.gui.add_slider("frame", int(numbers[0]), int(max(numbers[-1], numbers[0] + 1)),
                                                max(step, 1), int(numbers[0]), disabled=len(cams) == 1)
            self.play = server.gui.add_button("Play", disabled=len(cams) == 1)
            self.status = server.gui.add_markdown("")
        with server.gui.add_folder("Camera"):
            self.follow = server.gui.add_checkbox("follow clip camera", True,
                                                  hint="move with the clip's camera; off: orbit freely")
            self.to_clip = server.gui.add_button("Go to clip camera")
        self.frustum = server.scene.add_camera_frustum("/clip_camera", fov=1.0, aspect=cams.width / cams.height,
                                                       scale=self._extent / 10, color=(40, 160, 255), visible=False)
        with server.gui.add_folder("Layers", visible=bool(view.layers)):
            self.layer_boxes = [server.gui.add_checkbox(Path(name).name, True) for name in layer_names]
        self._build_selection_gui()

        self.slider.on_update(lambda _: self.show(self.slider.value))
        self.play.on_click(lambda _: self._toggle_play())
        self.follow.on_update(lambda _: self._follow_changed())
        self.to_clip.on_click(lambda event: self._set_camera(event.client))
        for j, box in enumerate(self.layer_boxes, start=1):
            box.on_update(lambda _, j=j, box=box: setattr(self._nodes[j], "visible", box.value))
        server.on_client_connect(self._connected)

        self._playing = False
        self._player = threading.Thread(target=self._play_loop, name="tomgs-view-play", daemon=True)
        self._player.start()
        self.show(int(numbers[0]))

    # -- frames ---------------------------------------------------------------------------------

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "::", "") else self.host
        return f"http://{host}:{self.port}"

    @property
    def position(self) -> int:
        return self._position

    def show(self, frame_number: int) -> None:
        """Show the scene frame nearest `frame_number`, as moving the time slider there does."""
        with self._lock:
            k = self.view.position_of(frame_number)
            number = int(self.view.cameras.frame_indices[k])
            if self.slider.value != number:
                self.slider.value = number  # its callback (on this thread) comes back here
                return
            if k != self._shown:
                self._draw(k)

    def _draw(self, k: int) -> None:
        start = time.perf_counter()
        payload = self.view.frame(k)
        built = time.perf_counter()
        with self.server.atomic():
            for node, splats in zip(self._nodes, payload):
                unit = splats.unit()
                node.set_gaussians(splats.centers / unit, splats.covariances / unit**2, splats.rgbs,
                                   splats.opacities)
                node.scale = unit
        sent = time.perf_counter()
        self._position = self._shown = k
        self._alive = payload[0].indices
        if self.timings["first_payload"] is None:
            self.timings["first_payload"] = sent
        self.timings["payloads"].append(dict(build_s=built - start, send_s=sent - built,
                                             splats=sum(map(len, payload))))
        cams = self.view.cameras
        self.status.content = (f"frame {int(cams.frame_indices[k])} ({k + 1} of {len(cams)}), "
                               f"t = {cams.times[k]:.4f}: {len(payload[0]):,} Gaussians alive"
                               + "".join(f", layer {j}: {len(p):,}" for j, p in enumerate(payload[1:], 1)))
        if self.follow.value:
            for client in self.server.get_clients().values():
                self._set_camera(client)
            self._initial_camera()
        else:
            self._show_frustum()
        self._update_selection(announce=False)

    def _initial_camera(self) -> None:
        """Clients that connect later start at the current frame's clip camera."""
        cam = clip_camera(self.view.cameras, self._position)
        initial = self.server.initial_camera
        initial.fov, initial.up = cam["fov"], cam["up"]
        initial.position, initial.look_at = cam["position"], cam["look_at"]

    def _set_camera(self, client) -> None:
        if client is None or not _camera_known(client):
            return
        cam = clip_camera(self.view.cameras, self._position)
        with client.atomic():
            client.camera.fov = cam["fov"]
            client.camera.position = cam["position"]
            client.camera.look_at = cam["look_at"]
            client.camera.up_direction = cam["up"]

    def _connected(self, client) -> None:
        """A new browser: once it has told us its camera, put it at the clip's camera."""
        client.camera.near, client.camera.far = NEAR, FAR
        deadline = time.monotonic() + 10.0
        while not _camera_known(client) and time.monotonic() < deadline and not self._stopped.is_set():
            time.sleep(0.05)
        with self._lock:
            if self.follow.value:
                self._set_camera(client)

    def _follow_changed(self) -> None:
        with self._lock:
            if self.follow.value:
                for client in self.server.get_clients().values():
                    self._set_camera(client)
            self._show_frustum()

    def _show_frustum(self) -> None:
        """The clip camera as a frustum, while the view is free to orbit away from it."""
        cams, k = self.view.cameras, self._position
        cam = clip_camera(cams, k)
        c2w = cams.c2w[k]
        self.frustum.fov, self.frustum.aspect = cam["fov"], cams.width / cams.height
        self.frustum.wxyz = rotmat_to_quat(c2w[:3, :3] / np.linalg.norm(c2w[:3, :3], axis=0))
        self.frustum.position = c2w[:3, 3]
        self.frustum.visible = not self.follow.value

    def _toggle_play(self) -> None:
        with self._lock:
            self._playing = not self._playing
            self.play.label = "Pause" if self._playing else "Play"

    def _play_loop(self) -> None:
        """Advance one frame per 1/fps while playing (slower when a frame takes longer), looping."""
        while not self._stopped.wait(1.0 / self.fps):
            if self._playing:
                with self._lock:
                    k = (self._position + 1) % len(self.view.cameras)
                    self.show(int(self.view.cameras.frame_indices[k]))

    # -- selection ------------------------------------------------------------------------------

    def _build_selection_gui(self) -> None:
        server, extent, step = self.server, self._extent, self._extent / 100
        sizes = self.view.scene.model.scales.detach().cpu().numpy()
        self._point_size = float(np.median(sizes)) if len(sizes) else extent / 1000
        with server.gui.add_folder("Select"):
            self.shape = server.gui.add_dropdown("shape", ("off", *SHAPES), initial_value="off")
            self.centre = server.gui.add_vector3("centre", tuple(self._middle), step=step)
            self.size = server.gui.add_vector3("box sides", (extent / 4,) * 3, step=step)
            self.radius = server.gui.add_number("radius", extent / 8, step=step)
            self.now_only = server.gui.add_checkbox("alive at this frame only", False,
                                                    hint="adds --select time:t,t of the current frame")
            self.select_text = server.gui.add_text("tomgs edit", "", disabled=True, multiline=True)
            self.select_count = server.gui.add_markdown("")
        self.gizmo = server.scene.add_transform_controls("/select", scale=extent / 4, disable_rotations=True,
                                                         position=self._middle, visible=False)
        self._box_node = self._sphere_node = self._points = None
        for handle in (self.shape, self.size, self.radius, self.now_only):
            handle.on_update(lambda _: self._update_selection(announce=True))
        self.centre.on_update(lambda _: self._centre_typed())
        # live highlight while dragging; the text is printed once, on release
        self.gizmo.on_update(lambda event: self._gizmo_moved(announce=event.phase == "end"))

    def _centre_typed(self) -> None:
        with self._lock:
            if self._syncing:
                return
            self.gizmo.position = self.centre.value
            self._update_selection(announce=True)

    def _gizmo_moved(self, announce: bool) -> None:
        with self._lock:
            self._syncing = True
            try:
                self.centre.value = tuple(float(v) for v in self.gizmo.position)
            finally:
                self._syncing = False
            self._update_selection(announce)

    def selection_texts(self) -> list[str]:
        """The `--select` texts of the shape placed in the viewer (none when the shape is off)."""
        shape = self.shape.value
        if shape not in SHAPES:
            return []
        texts = [selector_text(shape, self.centre.value, self.size.value if shape == "box" else self.radius.value)]
        if self.now_only.value:
            texts.append(time_text(self.view.cameras.times[self._position]))
        return texts

    def _update_selection(self, announce: bool) -> None:
        """Redraw the shape, highlight the selected Gaussians alive at this frame, show the option text;
        print it too when `announce` and it changed."""
        with self._lock:
            texts = self.selection_texts()
            shape = self.shape.value
            self.gizmo.visible = shape in SHAPES
            for node in (self._box_node, self._sphere_node, self._points):
                if node is not None:
                    node.remove()
            self._box_node = self._sphere_node = self._points = None
            if not texts:
                self.select_text.value, self.select_count.content = "", ""
                return
            if shape == "box":
                self._box_node = self.server.scene.add_box("/select/box", color=SELECTION_COLOR,
                                                           dimensions=tuple(np.abs(self.size.value)), wireframe=True)
            else:
                self._sphere_node = self.server.scene.add_icosphere("/select/sphere", abs(self.radius.value),
                                                                    color=SELECTION_COLOR, wireframe=True)
            model, cams = self.view.scene.model, self.view.cameras
            picked = select_with(model, cams, texts)
            shown = np.intersect1d(picked, self._alive)
            if shown.size:
                points = model.means.detach()[torch.as_tensor(shown)].cpu().numpy()
                self._points = self.server.scene.add_point_cloud(
                    "/selected", points, colors=SELECTION_COLOR, point_size=self._point_size, point_shape="circle")
            number = int(cams.frame_indices[self._position])
            summary = f"{picked.size:,} Gaussians, {shown.size:,} alive at frame {number}"
            self.select_text.value = f"tomgs edit {shlex.quote(self.scene_name)} {option_text(texts)} -o edited.ply"
            self.select_count.content = summary
            line = f"{option_text(texts)}  # {summary}"
            if announce and option_text(texts) != self._printed:
                self._printed = option_text(texts)
                self.echo(line)

    # -- life -------------------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop playing and the server (idempotent)."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        self._player.join(timeout=5.0)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "Server stopped"
            self.server.stop()

    def serve_forever(self) -> None:
        """Block until Ctrl-C or SIGTERM (from the main thread), then stop the server."""
        main = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, _interrupt) if main else None
        try:
            while not self._stopped.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            if main:
                signal.signal(signal.SIGTERM, previous)
            self.stop()


def open_viewer(scene_path, layer_paths=(), *, host: str = "127.0.0.1", port: int = 8080, device="auto",
                echo=print) -> Viewer:
    """Load SCENE and its layers (checked as `tomgs render --layer` checks them) and start a viewer on
    host:port (0: any free port; a busy port: the next free one). InputError for bad input."""
    require_viser()
    from tomgs.io.scene import load_scene
    from tomgs.render.layers import check_layers
    from tomgs.runtime import resolve_device

    if not 0 <= int(port) <= 65535:
        raise InputError(f"--port must be 0..65535 (0: any free port), got {port}")
    dev = resolve_device(device)
    _check_address(host)
    scene = load_scene(scene_path)
    layers = [load_scene(path) for path in layer_paths]
    check_layers(scene.cameras, [layer.cameras for layer in layers], [str(p) for p in layer_paths])
    return Viewer(ViewScene(scene, layers, dev), str(scene_path), host, int(port), [str(p) for p in layer_paths],
                  echo)


def _check_address(host: str) -> None:
    """InputError unless a server can listen on `host` (viser would retry a bad one port after port)."""
    import socket

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as e:
        raise InputError(f"--host {host}: cannot listen there ({e.strerror or e}); give 127.0.0.1 (this machine "
                         "only), 0.0.0.0 (every network) or an address of this machine") from None
