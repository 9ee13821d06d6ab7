"""Real-world video variants, made here from a small source (tests/videos.py): each reads every
frame it shows, upright, in order, or is refused in one line (exit 2) naming what is wrong and the fix."""

from __future__ import annotations

import av
import numpy as np
import pytest
from click.testing import CliRunner

from tests.videos import H, W, cut, damage, encode, frame_numbers, hide_last, picture, rotate, stream_copy
from tomgs.cli import main
from tomgs.errors import InputError
from tomgs.io import read_video
from tomgs.io.video import probe_source

HEVC = "libx265" in av.codecs_available
VFR = np.cumsum([0] + [100 if k % 3 == 0 else 33 for k in range(1, 40)]).tolist()  # ms: every third frame late


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """name -> (path, the frame numbers it shows, its (height, width) as shown)."""
    d = tmp_path_factory.mktemp("videos")
    source = encode(d / "source.mp4", 87)
    trim = stream_copy(source, d / "trim.mp4", 26)
    made = {
        "source (B-frames, moov at the end)": (source, range(87)),
        "trimmed start (stream copy)": (trim, range(26, 87)),
        "trimmed start and end": (stream_copy(source, d / "trim2.mp4", 13, 70), range(13, 70)),
        "edit list hides the last frame": (hide_last(trim, d / "hidden.mp4"), range(26, 86)),
        "edit list hides the last 3": (hide_last(trim, d / "hidden3.mp4", 3), range(26, 84)),
        "H.264 B-frames in AVI": (encode(d / "bf.avi", 87), range(87)),
        "H.264 B-frames in AVI, 40": (encode(d / "bf40.avi", 40), range(40)),
        "H.264 in MKV": (encode(d / "h264.mkv", 40), range(40)),
        "VP9 in WebM": (encode(d / "vp9.webm", 40, codec="libvpx-vp9"), range(40)),
        "MOV": (encode(d / "clip.mov", 40), range(40)),
        "audio stream first": (encode(d / "audio.mp4", 40, audio_first=True), range(40)),
        "fragmented MP4": (encode(d / "frag.mp4", 40, container_options={"movflags": "frag_keyframe+empty_moov"}),
                           range(40)),
        "moov at the start": (encode(d / "fast.mp4", 40, container_options={"movflags": "faststart"}), range(40)),
        "60 fps": (encode(d / "fps60.mp4", 40, rate=60), range(40)),
        "full range": (encode(d / "full.mp4", 40, pix_fmt="yuvj420p"), range(40)),
        "variable frame rate": (encode(d / "vfr.mp4", 40, stamps=VFR), range(40)),
        "853x479": (encode(d / "odd.mp4", 6, size=(853, 479), pix_fmt="yuv444p"), range(6), (479, 853)),
        "one frame": (encode(d / "one.mp4", 1), range(1)),
        "two frames": (encode(d / "two.mp4", 2), range(2)),
    }
    for degrees in (90, 180, 270):
        stored = encode(d / f"turned{degrees}.mp4", 20, turn=degrees // 90, bframes=0)
        made[f"display rotation {degrees}"] = (rotate(stored, d / f"rot{degrees}.mp4", degrees), range(20))
    if HEVC:
        made["HEVC"] = (encode(d / "hevc.mp4", 40, codec="libx265"), range(40))
        made["HEVC 10-bit"] = (encode(d / "hevc10.mp4", 40, codec="libx265", pix_fmt="yuv420p10le"), range(40))
    for name, base in [("MP4", source), ("MP4, moov first", made["moov at the start"][0]),
                       ("MKV", made["H.264 in MKV"][0]), ("WebM", made["VP9 in WebM"][0]),
                       ("AVI", made["H.264 B-frames in AVI, 40"][0]), ("fragmented MP4", made["fragmented MP4"][0])]:
        for percent in (50, 90):
            made[f"{name} cut at {percent}%"] = (cut(base, d / f"cut{percent}_{base.name}", percent), None)
    for percent in (23, 65):
        made[f"fragmented MP4 cut at {percent}%"] = (cut(made["fragmented MP4"][0], d / f"cut{percent}_frag.mp4",
                                                          percent), None)
    made["fragmented MP4 cut in its last index"] = (cut(made["fragmented MP4"][0], d / "cut99_frag.mp4", 99), range(40))
    made["MP4, moov first cut at 99%"] = (cut(made["moov at the start"][0], d / "cut99_fast.mp4", 99), None)
    made["a damaged packet"] = (damage(source, d / "damaged.mp4", 40), None)
    made["a keyframe zeroed"] = (damage(source, d / "zeroed.mp4", 20, zero=True), None)
    made["a damaged packet in MKV"] = (damage(made["H.264 in MKV"][0], d / "damaged.mkv", 25), None)
    return {name: (entry[0], entry[1], entry[2] if len(entry) > 2 else (H, W)) for name, entry in made.items()}


READS = ["source (B-frames, moov at the end)", "trimmed start (stream copy)", "trimmed start and end",
         "edit list hides the last frame", "edit list hides the last 3", "H.264 B-frames in AVI",
         "H.264 B-frames in AVI, 40", "H.264 in MKV", "VP9 in WebM", "MOV", "audio stream first", "fragmented MP4",
         "fragmented MP4 cut in its last index", "moov at the start", "60 fps", "full range", "variable frame rate",
         "853x479", "one frame", "two frames", "display rotation 90", "display rotation 180", "display rotation 270"] \
    + (["HEVC", "HEVC 10-bit"] if HEVC else [])
DAMAGED = [f"{name} cut at {percent}%" for name in ("MP4", "MP4, moov first", "MKV", "WebM", "AVI", "fragmented MP4")
           for percent in (50, 90)] + ["fragmented MP4 cut at 23%", "fragmented MP4 cut at 65%",
                                       "MP4, moov first cut at 99%", "a damaged packet", "a keyframe zeroed",
                                       "a damaged packet in MKV"]


@pytest.mark.parametrize("name", READS)
def test_every_shown_frame_reads_upright_and_in_order(corpus, name):
    """A stream-copy trim (the packets from the keyframe before the cut, the lead-in hidden by the
    edit list), a phone's edit list that hides the last frames, B-frames in an AVI (stored with
    decode-order times), other containers and codecs, turned frames: every frame shown is read once,
    in order, upright (the white block at the top left); the count from the index agrees, and a
    range reads the same frames."""
    path, shown, size = corpus[name]
    shown = list(shown)
    clip = read_video(path)
    assert frame_numbers(clip.frames) == shown
    assert clip.frames.shape[1:3] == size and clip.frames[:, 1, 1].min() > 200  # upright
    drawn = np.stack([picture(k, size[1], size[0]) for k in shown])
    assert np.abs(clip.frames.astype(int) - drawn).mean() < 3  # the source's colours (full range, 10-bit)
    assert clip.indices.tolist() == list(range(len(shown))) and clip.source_frames == len(shown)
    hides = "trimmed" in name or "edit list" in name
    assert [n for n in clip.notes if "edit list hides" in n] == clip.notes and len(clip.notes) == hides
    source = probe_source(path)
    assert (source.frames, source.height, source.width) == (len(shown), *size)
    if len(shown) > 30:
        assert frame_numbers(read_video(path, frames="10:20").frames) == shown[10:20]
        assert frame_numbers(read_video(path, frames="23:").frames) == shown[23:]


@pytest.mark.parametrize("name", DAMAGED)
def test_a_damaged_file_is_refused_or_read_whole(corpus, name):
    """A file cut short (an MKV or WebM too, which has no frame count to check) or with a damaged
    packet is refused in one line naming it and the fix, or read whole where the decoder mends the
    damage: never a shorter clip without a word."""
    path, _, _ = corpus[name]
    try:
        clip = read_video(path)
    except InputError as e:
        message = str(e)
        assert path.name in message and "\n" not in message and message.count(str(path)) == 1
        assert any(word in message for word in ("truncated", "cut short", "corrupt")), message
        assert any(fix in message for fix in ("copy it again", "re-encode")), message
        return
    assert "damaged" in name and len(clip) == 87 and clip.source_frames == 87


@pytest.mark.parametrize("name", ["MKV cut at 50%", "WebM cut at 90%", "a damaged packet in MKV"])
def test_a_damaged_file_is_exit_2_at_every_command(corpus, name, tmp_path):
    """poses and fit answer a damaged file with exit 2 and one line, and write nothing."""
    path = corpus[name][0]
    for args in (["poses", path, "-o", tmp_path / "cams.json", "--method", "identity"],
                 ["fit", path, "-o", tmp_path / "s.ply", "--iterations", "1", "--device", "cpu",
                  "--poses", "identity"]):
        result = CliRunner().invoke(main, [str(a) for a in args])
        assert result.exit_code == 2, result.output
        assert path.name in result.output and "Traceback" not in result.output
    assert not list(tmp_path.iterdir())


def test_a_clip_whose_edit_list_hides_frames_says_so(corpus, tmp_path):
    """poses reads the 60 frames shown and says why other tools count 67."""
    path = corpus["edit list hides the last frame"][0]
    result = CliRunner().invoke(main, ["poses", str(path), "-o", str(tmp_path / "cams.json"), "--method", "identity"])
    assert result.exit_code == 0, result.output
    assert "60 frames shown of 67 stored: the file's edit list hides 7 frames" in result.output
    assert "60 frames" in result.output.splitlines()[-1]


@pytest.mark.parametrize("name, facts", [
    ("source (B-frames, moov at the end)", "30 fps"), ("60 fps", "60 fps"),
    ("variable frame rate", "variable frame rate"),
    ("display rotation 270", "30 fps, turned 270\N{DEGREE SIGN} as the file says")])
def test_the_source_says_its_frame_rate_and_rotation(corpus, name, facts):
    assert probe_source(corpus[name][0]).facts() == facts


def test_the_fit_plan_says_what_the_file_says_of_itself(corpus, tmp_path):
    """The plan line, before any frame is decoded: frames, size as shown (stored 48x64), frame rate,
    rotation."""
    path = corpus["display rotation 90"][0]
    result = CliRunner().invoke(main, ["fit", str(path), "-o", str(tmp_path / "s.ply"), "--iterations", "1",
                                       "--device", "cpu", "--poses", "identity"])
    assert result.exit_code == 0, result.output
    plan = next(line for line in result.output.splitlines() if line.startswith("plan: "))
    assert plan.startswith("plan: 20 frames of 64x48 (30 fps, turned 90\N{DEGREE SIGN} as the file says) on cpu")


def test_eval_refuses_a_cut_copy_of_the_fitted_video(corpus, tmp_path):
    """eval reads a video by the same rules: a cut copy of the clip a scene was fitted on is refused
    as truncated in one line (exit 2), the whole one compared."""
    path = corpus["H.264 in MKV"][0]
    scene = tmp_path / "s.ply"
    fit = CliRunner().invoke(main, ["fit", str(path), "-o", str(scene), "--iterations", "1", "--device", "cpu",
                                    "--poses", "identity", "-q"])
    assert fit.exit_code == 0, fit.output
    for name in ("MKV cut at 50%", "MKV cut at 90%"):
        result = CliRunner().invoke(main, ["eval", str(scene), str(corpus[name][0])])
        assert result.exit_code == 2 and "truncated" in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1
    assert CliRunner().invoke(main, ["eval", str(scene), str(path)]).exit_code == 0
