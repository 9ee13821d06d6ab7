"""Videos tomgs writes play where people look at them: H.264 yuv420p MP4 with its index first (a
browser streams it), frames that decode back to what was written, odd sizes padded to even."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from tomgs.io import read_video, write_frames


def frames(n=12, w=65, h=37):
    """A gradient that moves: smooth content, as rendered frames are."""
    y, x = np.mgrid[0:h, 0:w]
    return [np.stack([(x * 3 + 10 * k) % 256, (y * 5 + 7 * k) % 256, np.full_like(x, 128)], -1).astype(np.uint8)
            for k in range(n)]


@pytest.mark.parametrize("suffix", [".mp4", ".mov", ".mkv"])
def test_h264_yuv420p_round_trip(tmp_path, suffix):
    import av

    written = frames()
    path = tmp_path / f"clip{suffix}"
    assert write_frames(written, path, fps=24.0) == len(written)
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.format.name == "yuv420p"
        assert (stream.width, stream.height) == (66, 38)  # odd sides padded to even for yuv420p
        assert abs(float(stream.average_rate) - 24.0) < 1e-6
        decoded = [f.to_ndarray(format="rgb24")[:37, :65] for f in container.decode(stream)]
    assert len(decoded) == len(written)
    error = np.mean([np.abs(a.astype(float) - b).mean() for a, b in zip(decoded, written)])
    assert error < 3.0, error  # CRF 18 of smooth content: a few levels of 255 at most
    clip = read_video(path)  # and tomgs reads its own output (OpenCV's decoder)
    assert len(clip) == len(written)


def test_mp4_index_comes_first(tmp_path):
    """`moov` before `mdat`: a browser can start playing before the file has loaded."""
    path = tmp_path / "clip.mp4"
    write_frames(frames(), path)
    data = path.read_bytes()
    assert 0 <= data.find(b"moov") < data.find(b"mdat")


def test_avi_stays_motion_jpeg(tmp_path):
    import av

    path = tmp_path / "clip.avi"
    write_frames(frames(4, 32, 24), path)
    with av.open(str(path)) as container:
        assert container.streams.video[0].codec_context.name == "mjpeg"


def test_chromium_plays_the_mp4(tmp_path, chromium):
    """A real browser loads and plays the file (OpenCV's mp4v gave DEMUXER_ERROR_NO_SUPPORTED_STREAMS)."""
    write_frames(frames(24, 64, 36), tmp_path / "clip.mp4", fps=24.0)
    page = tmp_path / "index.html"
    page.write_text("""<html><body><video id="v" muted></video><pre id="out">pending</pre><script>
const v = document.getElementById('v'), out = document.getElementById('out');
v.onerror = () => { out.textContent = 'error ' + v.error.message; };
v.onloadeddata = () => v.play().then(
  () => { out.textContent = 'played ' + v.videoWidth + 'x' + v.videoHeight + ' ' + v.duration.toFixed(2); },
  e => { out.textContent = 'play failed ' + e; });
v.src = 'clip.mp4';
</script></body></html>""")
    result = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files",
                             "--autoplay-policy=no-user-gesture-required", "--virtual-time-budget=8000",
                             "--dump-dom", page.as_uri()], capture_output=True, text=True, timeout=120)
    assert "played 64x36 1.00" in result.stdout, result.stdout[-500:]


def test_rendered_mp4_keeps_every_frame_within_36_db_of_the_pngs(tmp_path):
    """`tomgs demo` to an MP4 and to PNGs: the MP4 holds every frame, each decoded back at least 36 dB
    from its PNG. yuv420p halves chroma: on the demo's checkerboards at 320x180 the colour conversion
    alone costs 41.3 dB and CRF 18 gives 37.4 dB at worst (160x90: 36.9 dB lossless, 32.8 dB at CRF
    18; 640x360: 41.0 dB at CRF 18), so CRF 18 holds from 320x180 up."""
    import av
    import cv2
    from click.testing import CliRunner

    from tomgs.cli import main

    for output in ("demo.mp4", "frames"):
        result = CliRunner().invoke(main, ["demo", "--frames", "16", "--size", "320x180", "-o", str(tmp_path / output)])
        assert result.exit_code == 0, result.output
    pngs = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in sorted((tmp_path / "frames").glob("*.png"))]
    with av.open(str(tmp_path / "demo.mp4")) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(container.streams.video[0])]
    assert len(decoded) == len(pngs) == 16
    for png, frame in zip(pngs, decoded):
        mse = np.mean((png.astype(np.float64) - frame) ** 2)
        assert 10 * np.log10(255.0**2 / mse) >= 36.0
