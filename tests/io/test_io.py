"""Reading clips: video files, frame folders, masks, ranges, resizing, and every bad input."""

import cv2
import numpy as np
import pytest

from tomgs.io import InputError, parse_frames, read_video


def _frame(k, h=48, w=64):
    """A frame whose pixel (0, 0) encodes k (so the order can be checked after reading)."""
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = 10 * k
    img[..., 1] = np.arange(w, dtype=np.uint8)[None, :]
    img[..., 2] = 200
    return img


@pytest.fixture
def folder(tmp_path):
    d = tmp_path / "frames"
    d.mkdir()
    for k in range(12):  # names that sort wrongly as text: f2 after f10
        cv2.imwrite(str(d / f"f{k}.png"), cv2.cvtColor(_frame(k), cv2.COLOR_RGB2BGR))
    m = tmp_path / "masks"
    m.mkdir()
    for k in range(12):
        mask = np.zeros((48, 64), np.uint8)
        mask[:, k:k + 5] = 255
        cv2.imwrite(str(m / f"m{k}.png"), mask)
    return d, m


def test_folder_natural_order_range_and_masks(folder):
    d, m = folder
    v = read_video(d, masks=m)
    assert v.frames.shape == (12, 48, 64, 3) and v.frames.dtype == np.uint8
    assert list(v.frames[:, 0, 0, 0]) == [10 * k for k in range(12)]
    assert v.frames[0, 0, 0, 2] == 200  # RGB, not BGR
    assert v.masks.shape == (12, 48, 64) and v.masks.dtype == bool
    assert v.masks[3, 0, 3] and not v.masks[3, 0, 2]
    assert np.allclose(v.times, np.arange(12) / 11)

    v = read_video(d, frames="2:10:3", masks=m)
    assert list(v.indices) == [2, 5, 8]
    assert list(v.frames[:, 0, 0, 0]) == [20, 50, 80]
    assert v.masks[1, 0, 5] and not v.masks[1, 0, 4]  # mask of source frame 5
    assert list(read_video(d, frames="::2").indices) == list(range(0, 12, 2))
    assert list(read_video(d, frames="-3:").indices) == [9, 10, 11]


def test_resize_to_max_side(folder):
    d, m = folder
    v = read_video(d, max_side=32, masks=m)
    assert v.frames.shape == (12, 24, 32, 3) and v.masks.shape == (12, 24, 32)
    assert read_video(d, max_side=100).frames.shape[1:3] == (48, 64)  # never upscaled


@pytest.mark.parametrize("name, codec", [("clip.avi", "MJPG"), ("clip.mp4", "mp4v")])
def test_video_file(tmp_path, name, codec):
    path = tmp_path / name
    wr = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 25, (64, 48))
    assert wr.isOpened()
    for k in range(9):
        wr.write(cv2.cvtColor(_frame(k), cv2.COLOR_RGB2BGR))
    wr.release()
    v = read_video(path, frames="1:8:2")
    assert v.frames.shape == (4, 48, 64, 3)
    assert list(v.indices) == [1, 3, 5, 7]
    assert abs(v.fps - 25) < 1e-6
    assert np.abs(v.frames[:, 10, 10, 0].astype(int) - [10, 30, 50, 70]).max() <= 8  # lossy codecs


def test_parse_frames():
    assert parse_frames("0:80") == slice(0, 80, None)
    assert parse_frames("::2") == slice(None, None, 2)
    assert parse_frames("7") == slice(7, 8)
    assert parse_frames(None) == slice(None)


@pytest.mark.parametrize("spec", ["a:b", "1:2:3:4", "::0", "::-1", "1.5:3"])
def test_bad_range(folder, spec):
    with pytest.raises(InputError, match="range"):
        read_video(folder[0], frames=spec)


def test_bad_inputs(tmp_path, folder):
    d, m = folder
    with pytest.raises(InputError, match="does not exist"):
        read_video(tmp_path / "nope.mp4")
    corrupt = tmp_path / "broken.mp4"
    corrupt.write_bytes(b"\x00not a video at all" * 100)
    with pytest.raises(InputError, match="broken.mp4"):
        read_video(corrupt)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no jpg/png"):
        read_video(empty)
    with pytest.raises(InputError, match="selects no frames"):
        read_video(d, frames="20:30")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(InputError, match="neither a video"):
        read_video(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="max_side"):
        read_video(d, max_side=0)
    # masks: wrong count, wrong size, missing folder
    (m / "m11.png").unlink()
    with pytest.raises(InputError, match="11 masks but the clip has 12"):
        read_video(d, masks=m)
    cv2.imwrite(str(m / "m11.png"), np.zeros((20, 20), np.uint8))
    with pytest.raises(InputError, match="20x20"):
        read_video(d, masks=m)
    with pytest.raises(InputError, match="mask folder"):
        read_video(d, masks=tmp_path / "nomasks")
    bad = d / "f5.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(InputError, match="f5.png"):
        read_video(d)
    assert issubclass(InputError, ValueError)
