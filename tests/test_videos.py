"""Real-world video variants, made here from a small source (tests/videos.py): each reads every
frame it shows, upright, in order, or is refused in one line (exit 2) naming what is wrong and the fix."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from tests.videos import encode, frame_numbers, hide_last, stream_copy
from tomgs.cli import main
from tomgs.errors import InputError
from tomgs.io import read_video
from tomgs.io.video import probe_source


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """name -> (path, the frame numbers it shows)."""
    d = tmp_path_factory.mktemp("videos")
    source = encode(d / "source.mp4", 87)
    made = {"source": (source, list(range(87)))}
    made["trimmed start"] = (stream_copy(source, d / "trim.mp4", 26), list(range(26, 87)))
    made["trimmed start and end"] = (stream_copy(source, d / "trim2.mp4", 13, 70), list(range(13, 70)))
    made["edit list hides the last frame"] = (hide_last(made["trimmed start"][0], d / "hidden.mp4"),
                                              list(range(26, 86)))
    made["edit list hides the last 3"] = (hide_last(made["trimmed start"][0], d / "hidden3.mp4", 3),
                                          list(range(26, 84)))
    return made


READS = ["source", "trimmed start", "trimmed start and end", "edit list hides the last frame",
         "edit list hides the last 3"]


@pytest.mark.parametrize("name", READS)
def test_every_shown_frame_reads_in_order(corpus, name):
    """A stream-copy trim (the packets from the keyframe before the cut, the lead-in hidden by the
    edit list) and a phone's edit list that hides the last frames read every frame they show, and
    nothing they hide; the count from the index agrees, and a range reads the same frames."""
    path, shown = corpus[name]
    clip = read_video(path)
    assert frame_numbers(clip.frames) == shown
    assert clip.indices.tolist() == list(range(len(shown))) and clip.source_frames == len(shown)
    assert probe_source(path).frames == len(shown)
    part = read_video(path, frames="10:20")
    assert frame_numbers(part.frames) == shown[10:20]
