"""`tomgs view`: the per-frame payload, layers placed in the base's world, selections that `tomgs edit`
reproduces, the command's life (URL, Ctrl-C, bad input), and headless Chromium drawing what
`tomgs render` draws."""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tomgs.cli import main
from tomgs.demo import demo_scene
from tomgs.edit.selection import parse_selector
from tomgs.geometry import covariances, rotmat_to_quat
from tomgs.io.scene import Scene, load_scene, save_scene
from tomgs.render.layers import NEAR, plane_cameras, render_layers
from tomgs.model import GaussianModel, rgb_to_sh_dc, stored_opacities, stored_scales, stored_t_scales
from tomgs.render.frame import rasterize
from tomgs.temporal import frozen_at, opacity_at

pytest.importorskip("viser", reason='the viewer is the optional extra [view]: pip install "tomgs[view]"')

from tomgs.viewer import server as view  # noqa: E402  (after the skip: importing it needs no viser, using it does)

BACKGROUND = (0.05, 0.05, 0.08)


def _model(g: dict) -> GaussianModel:
    n = len(g["means"])
    return GaussianModel(g["means"], g["quats"], stored_scales(g["scales"]), stored_opacities(g["opacities"]),
                         rgb_to_sh_dc(g["colors"]), torch.zeros(n, 0, 3), g["t_means"], stored_t_scales(g["t_scales"]))


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The procedural demo (a ball crossing a room, 12 frames at 160x90) as a scene file."""
    g, cams = demo_scene(12, 160, 90)
    path = tmp_path_factory.mktemp("view") / "demo.ply"
    save_scene(path, _model(g), cams, {"background": list(BACKGROUND), "fps": 12})
    return path


def _foreground(cams) -> Scene:
    """A layer with a foreground's cameras (the front plane camera, focal max(W, H), not the base's):
    flat Gaussians about the plane z = 0, each alive around its own time. Not on the plane itself:
    Gaussians at one depth composite in whatever order the sort leaves ties, in any renderer."""
    g = torch.Generator().manual_seed(3)
    n = 60
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([0.8, 0.4])
    quats = torch.nn.functional.normalize(torch.cat([torch.ones(n, 1), torch.zeros(n, 2),
                                                     torch.rand(n, 1, generator=g) - 0.5], 1), dim=1)
    scales = torch.cat([0.02 + 0.05 * torch.rand(n, 2, generator=g), torch.full((n, 1), 1e-8)], 1)
    layer = dict(means=torch.cat([xy, torch.linspace(-0.3, 0.3, n)[:, None]], 1), quats=quats, scales=scales,
                 opacities=0.5 + 0.45 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
                 t_means=torch.rand(n, generator=g), t_scales=torch.full((n,), 0.3))
    front, _ = plane_cameras(len(cams), cams.width, cams.height, cams.times, cams.frame_indices)
    return Scene(_model(layer), front)


def _as_rasterizer_inputs(splats: view.Splats) -> dict:
    """A payload back as the rasterizer takes it: each covariance as a rotation and three scales."""
    values, vectors = np.linalg.eigh(splats.covariances.astype(np.float64))
    vectors[np.linalg.det(vectors) < 0, :, 2] *= -1
    return dict(means=torch.from_numpy(splats.centers), quats=torch.from_numpy(rotmat_to_quat(vectors)).float(),
                scales=torch.from_numpy(np.sqrt(np.clip(values, 0, None))).float(),
                opacities=torch.from_numpy(splats.opacities[:, 0]), colors=torch.from_numpy(splats.rgbs),
                t_means=torch.zeros(len(splats)), t_scales=torch.ones(len(splats)))


def _render(g: dict, cams, k: int, background=None) -> torch.Tensor:
    """Frame k of `g` from camera k at its time (a payload's t_means are 0 and t_scales 1: drawn at
    t = 0 with exactly its baked opacities)."""
    payload = bool((g["t_means"] == 0).all() and (g["t_scales"] == 1).all())
    image, _, _ = rasterize(**g, viewmat=cams.viewmats("cpu")[k], K=cams.Ks("cpu")[k], width=cams.width,
                            height=cams.height, t=0.0 if payload else float(cams.times[k]), background=background)
    return image


# ---- the payload ---------------------------------------------------------------------------------

def test_payload_is_the_alive_gaussians_with_their_opacity_baked(demo):
    scene = load_scene(demo)
    viewed = view.ViewScene(scene)
    g = scene.model.render_inputs()
    for k in (0, 5, 11):
        splats, = viewed.frame(k)
        t = float(scene.cameras.times[k])
        frozen = frozen_at(g, t)
        at_t = opacity_at(g["opacities"].detach().double(), g["t_means"].detach().double(),
                          g["t_scales"].detach().double(), t)
        alive = np.flatnonzero((at_t >= 1 / 255).numpy())
        assert np.array_equal(splats.indices, alive) and 0 < len(alive) < len(scene.model)
        assert np.array_equal(splats.centers, frozen["means"].numpy())
        assert np.allclose(splats.opacities[:, 0], frozen["opacities"].numpy())
        assert np.allclose(splats.covariances, covariances(frozen["quats"], frozen["scales"]).numpy(), atol=1e-7)
        assert np.allclose(splats.rgbs, (0.28209479177387814 * frozen["colors"][:, 0] + 0.5).clamp(0, 1).numpy(),
                           atol=1e-6)


def test_payload_covariances_fit_float16_for_huge_and_tiny_gaussians():
    """viser sends covariances as float16: divided by unit^2 none overflows (a fitted background's
    largest Gaussians are thousands of times the median size), and the median one keeps its value
    while the range allows (float16 spans 1e9 between its smallest normal and largest value)."""
    for largest, normal in ((50.0, True), (3000.0, False)):
        sizes = np.concatenate([np.full(1000, 0.01), [largest]])
        covariances = np.eye(3)[None] * (sizes**2)[:, None, None]
        splats = view.Splats(np.zeros((len(sizes), 3), np.float32), covariances.astype(np.float32),
                             np.zeros((len(sizes), 3), np.float32), np.ones((len(sizes), 1), np.float32),
                             np.arange(len(sizes)))
        sent = (splats.covariances / splats.unit() ** 2).astype(np.float16)
        assert np.isfinite(sent).all()
        assert sent[0, 0, 0] > (np.finfo(np.float16).tiny if normal else 0)


def test_payload_renders_as_the_scene_from_the_clip_camera(demo):
    """The frozen cloud the browser gets is the frame: rasterized back, it equals `tomgs render`."""
    scene = load_scene(demo)
    k = 7
    splats, = view.ViewScene(scene).frame(k)
    ours = _render(_as_rasterizer_inputs(splats), scene.cameras, k)
    reference = _render(scene.model.render_inputs(), scene.cameras, k)
    assert (ours - reference).abs().max() < 2e-3


def test_a_layer_placed_in_the_base_world_looks_as_its_own_camera_sees_it(demo):
    """From the base camera, the mapped layer draws the image the layer's own camera draws (different
    intrinsics included), and with the base it composites as `tomgs render --layer` does."""
    base = load_scene(demo)
    layer = _foreground(base.cameras)
    assert not np.allclose(base.cameras.K, layer.cameras.K)
    viewed = view.ViewScene(base, [layer])
    for k in (1, 6, 10):
        base_splats, layer_splats = viewed.frame(k)
        assert len(layer_splats) > 10
        mapped = _render(_as_rasterizer_inputs(layer_splats), base.cameras, k)
        own = _render(layer.model.render_inputs(), layer.cameras, k)
        assert (mapped - own).abs().max() < 3e-3
        # in front of every base Gaussian, as compositing puts it
        w2c = base.cameras.viewmats()[k]
        ahead, layer_depth = (splats.centers @ w2c[2, :3] + w2c[2, 3] for splats in (base_splats, layer_splats))
        assert layer_depth.max() < ahead[ahead > NEAR].min()
        parts = [_as_rasterizer_inputs(splats) for splats in (base_splats, layer_splats)]
        together = {name: torch.cat([part[name] for part in parts]) for name in parts[0]}
        joint = _render(together, base.cameras, k, torch.tensor(BACKGROUND))
        (_, composite, _), = render_layers(base.model.render_inputs(), base.cameras, [k],
                                           [(layer.model.render_inputs(), layer.cameras)], background=BACKGROUND)
        assert (joint.clamp(0, 1) - composite).abs().max() < 5e-3


def test_clip_camera_is_the_scene_camera(demo):
    cams = load_scene(demo).cameras
    cam = view.clip_camera(cams, 3)
    assert np.allclose(cam["position"], cams.c2w[3, :3, 3])
    assert np.allclose(cam["look_at"] - cam["position"], cams.c2w[3, :3, 2])
    assert np.isclose(np.tan(cam["fov"] / 2) * 2 * cams.K[1, 1], cams.height)


# ---- selections --------------------------------------------------------------------------------

def test_selection_text_round_trips_through_tomgs_edit(demo, tmp_path):
    scene = load_scene(demo)
    means = scene.model.means.detach().double().numpy()
    centre, sides = np.array([0.3, 0.1, 4.8]), np.array([1.0, 0.8, 1.2])
    text = view.selector_text("box", centre, sides)
    parsed = parse_selector(text)
    assert parsed.kind == "box" and np.allclose(parsed.numbers, [*(centre - sides / 2), *(centre + sides / 2)])
    picked = view.select_with(scene.model, scene.cameras, [text])
    inside = np.flatnonzero((np.abs(means - centre) <= sides / 2 + 1e-9).all(1))
    assert np.array_equal(picked, inside) and 0 < len(picked) < len(means)

    sphere = view.selector_text("sphere", centre, 0.7)
    assert np.array_equal(view.select_with(scene.model, scene.cameras, [sphere]),
                          np.flatnonzero(np.linalg.norm(means - centre, axis=1) <= 0.7))
    now = view.time_text(scene.cameras.times[5])
    both = view.select_with(scene.model, scene.cameras, [text, now])
    alive = view.ViewScene(scene).frame(5)[0].indices
    assert np.array_equal(both, np.intersect1d(picked, alive))
    assert view.select_with(scene.model, scene.cameras, [view.selector_text("sphere", (0, 0, -50), 0.1)]).size == 0

    # what the viewer prints, pasted into `tomgs edit`, removes exactly what it highlighted
    options = view.option_text([text, now]).split()
    out = tmp_path / "removed.ply"
    result = CliRunner().invoke(main, ["edit", str(demo), "-o", str(out), *options, "--remove"])
    assert result.exit_code == 0, result.output
    assert len(load_scene(out).model) == len(means) - len(both)


def test_viewer_selection_gui_prints_the_option_text(demo):
    lines = []
    viewer = view.open_viewer(demo, port=0, device="cpu", echo=lines.append)
    try:
        viewer.show(6)
        assert viewer.position == 6 and viewer.slider.value == 6
        viewer.centre.value = (0.3, 0.1, 4.8)
        viewer.size.value = (1.0, 0.8, 1.2)
        viewer.shape.value = "box"
        viewer.now_only.value = True
        texts = viewer.selection_texts()
        assert texts == [view.selector_text("box", (0.3, 0.1, 4.8), (1.0, 0.8, 1.2)),
                         view.time_text(viewer.view.cameras.times[6])]
        assert lines[-1].startswith(view.option_text(texts) + "  # ")
        count = len(view.select_with(viewer.view.scene.model, viewer.view.cameras, texts))
        assert f"{count:,} Gaussians" in lines[-1] and view.option_text(texts) in viewer.select_text.value
        viewer.shape.value = "off"
        assert viewer.selection_texts() == [] and viewer.select_text.value == ""
    finally:
        viewer.stop()


# ---- the command ---------------------------------------------------------------------------------

def _start(*args) -> tuple[subprocess.Popen, str]:
    """`tomgs view ARGS --port 0` in a subprocess and the URL it prints."""
    proc = subprocess.Popen([sys.executable, "-m", "tomgs.cli", "view", *map(str, args), "--port", "0",
                             "--device", "cpu"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    match = re.search(r"http://\S+", line)
    if not match:
        proc.kill()
        raise AssertionError(f"no URL in {line!r}: {proc.stderr.read()}")
    return proc, match.group(0)


def test_view_prints_its_url_serves_the_client_and_stops_on_ctrl_c(demo):
    proc, url = _start(demo)
    try:
        with urllib.request.urlopen(url, timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read(4096).lower()
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stopped" in out and "Traceback" not in err


@pytest.mark.parametrize("args, message", [
    (["missing.ply"], "does not exist"),
    (["{demo}", "--host", "192.0.2.1"], "--host 192.0.2.1: cannot listen there"),
    (["{demo}", "--layer", "{layer}"], "layers must be fitted on the same frames"),
    (["{demo}", "--device", "tpu"], "device 'tpu'"),
])
def test_bad_input_exits_2(demo, tmp_path, args, message):
    g, cams = demo_scene(5, 160, 90)
    layer = tmp_path / "short.ply"
    save_scene(layer, _model(g), cams)
    result = CliRunner().invoke(main, ["view", *[a.format(demo=demo, layer=layer) for a in args], "--port", "0"])
    assert result.exit_code == 2 and message in result.output, result.output


def test_without_viser_it_says_how_to_install_it(demo, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser raises ImportError
    result = CliRunner().invoke(main, ["view", str(demo)])
    assert result.exit_code == 2 and 'pip install "tomgs[view]"' in result.output


# ---- in the browser ------------------------------------------------------------------------------

WIDTH, HEIGHT = 1280, 720  # the demo's 16:9, so the canvas shows exactly the clip's frame
PANEL_LEFT = 930  # viser's control panel floats over the canvas right of here
AXES_TOP = 650  # and its axes gizmo in the lower left corner, below here

# the page: close the software-WebGL notice, then type a frame number into the time slider's field
PAGE_JS = """(() => {
  const leaf = (text) => Array.from(document.querySelectorAll('body *')).find(
      e => e.children.length === 0 && e.textContent.trim().startsWith(text));
  let note = leaf('Software WebGL');
  while (note && !note.querySelector('button')) note = note.parentElement;
  if (note) note.querySelector('button').click();
  let row = leaf('frame');
  while (row && !row.querySelector('input.mantine-NumberInput-input')) row = row.parentElement;
  const input = row.querySelector('input.mantine-NumberInput-input');
  input.focus();
  input.select();
  return input.value;
})()"""


class Chromium:
    """Headless Chromium driven through the DevTools protocol (websockets comes with viser)."""

    def __init__(self, exe: str, profile, width: int, height: int):
        from websockets.sync.client import connect

        flags = ["--headless", "--no-sandbox", "--force-color-profile=srgb", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--disable-gpu-sandbox", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--user-data-dir={profile}", f"--window-size={width},{height}", "--remote-debugging-port=0", "about:blank"]
        self.proc = subprocess.Popen([exe, *flags], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.exists() and port_file.read_text().count("\n")):
            assert self.proc.poll() is None and time.monotonic() < deadline, "chromium did not start"
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as answer:
            page = next(p for p in json.load(answer) if p["type"] == "page")
        self.socket = connect(page["webSocketDebuggerUrl"], max_size=None)
        self.ids = itertools.count(1)
        self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                  mobile=False)

    def call(self, method: str, **params):
        ident = next(self.ids)
        self.socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv(timeout=120))
            if message.get("id") == ident:
                assert "error" not in message, message
                return message["result"]

    def screenshot(self) -> np.ndarray:
        """RGB float32 [H,W,3] in [0, 1]."""
        import cv2

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255

    def settled(self, timeout: float = 120.0) -> np.ndarray:
        """A screenshot once two in a row are the same (the splats sorted and drawn)."""
        previous, deadline = None, time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(0.7)
            shot = self.screenshot()
            if previous is not None and np.array_equal(shot, previous):
                return shot
            previous = shot
        raise AssertionError("the page never settled")

    def type_frame(self, number: int) -> None:
        self.call("Runtime.evaluate", expression=PAGE_JS, returnByValue=True)
        self.call("Input.insertText", text=str(number))
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter", windowsVirtualKeyCode=13)

    def close(self) -> None:
        self.socket.close()
        os.killpg(self.proc.pid, signal.SIGTERM)
        self.proc.wait(timeout=30)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


@pytest.mark.slow
def test_chromium_shows_the_frames_tomgs_render_draws(demo, tmp_path, chromium):
    """Two frames typed into the time slider of the page: each screenshot is `tomgs render` of its
    frame from the clip camera at the canvas's size (PSNR > 30 dB over the canvas outside the panel;
    measured 41-46 dB: float16 covariances, 8-bit colours and viser's 1% alpha cut are the rest), far
    closer to it than to the other frame's render, and the two differ where the ball moved. The page
    opens on the first frame seen from the clip's first camera, in the colours `tomgs render` gives
    (the same 30 dB)."""
    import cv2

    scene = load_scene(demo)
    cams = scene.cameras.resized(WIDTH, HEIGHT)
    frames = (2, 9)
    renders = {k: frame.numpy() for k, frame, _ in render_layers(scene.model.render_inputs(), cams, [0, *frames],
                                                                background=BACKGROUND)}
    proc, url = _start(demo)
    browser = Chromium(chromium, tmp_path / "profile", WIDTH, HEIGHT)
    shots = {}
    try:
        browser.call("Page.navigate", url=url)
        browser.settled()
        browser.call("Runtime.evaluate", expression=PAGE_JS, returnByValue=True)  # the notice closed
        opened = browser.settled()
        cv2.imwrite(str(tmp_path / "opened.png"), (opened[..., ::-1] * 255).round().astype(np.uint8))
        for k in frames:
            browser.type_frame(int(scene.cameras.frame_indices[k]))
            shots[k] = browser.settled()
            cv2.imwrite(str(tmp_path / f"view_frame{k}.png"), (shots[k][..., ::-1] * 255).round().astype(np.uint8))
    finally:
        browser.close()
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=30)
    assert proc.returncode == 0

    canvas = np.s_[:AXES_TOP, :PANEL_LEFT]
    first = _psnr(opened[canvas], renders[0][canvas])
    assert first > 30.0 and first > _psnr(opened[canvas], renders[9][canvas]) + 5.0, f"opened: {first:.1f} dB"
    a, b = frames
    for k, other in ((a, b), (b, a)):
        match = _psnr(shots[k][canvas], renders[k][canvas])
        assert match > 30.0, f"frame {k}: {match:.1f} dB against its render"
        assert match > _psnr(shots[k][canvas], renders[other][canvas]) + 5.0
    moved = (np.abs(renders[a] - renders[b]).max(-1) > 0.2)[canvas]
    still = (np.abs(renders[a] - renders[b]).max(-1) < 0.01)[canvas]
    change = np.abs(shots[a] - shots[b]).max(-1)[canvas]
    assert moved.mean() > 0.02 and (change[moved] > 0.1).mean() > 0.8 and (change[still] < 0.05).mean() > 0.95
