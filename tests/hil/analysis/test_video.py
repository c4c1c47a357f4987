"""satgrasp video: the logged frames with the systems' models and the fused pose drawn."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from hil.analysis.video import VideoError, open_writer, render_video
from hil.cli import app
from tests.hil.logs.synthetic_log import make_trial, write_trial


@pytest.fixture(scope="module")
def log_with_frames(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "trial.mcap"
    write_trial(path, make_trial(seed=5), frames_every=20)
    return path


def test_render_video_writes_every_logged_frame_with_overlays(log_with_frames, tmp_path):
    out, frames = render_video(log_with_frames, tmp_path / "v.avi", codec="MJPG", fps=2.0)
    capture = cv2.VideoCapture(str(out))
    read = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        read.append(image)
    assert frames > 3 and len(read) == frames
    # the synthetic frames are grey: drawn overlays (models, axes, text) bring colour
    coloured = [np.ptp(image.astype(int), axis=2).max() > 60 for image in read]
    assert sum(coloured) >= frames - 1


def test_open_writer_refuses_a_codec_that_does_not_open(tmp_path):
    with pytest.raises(VideoError, match="codec"):
        open_writer(tmp_path / "x.nope", "ZZZZ", 5.0, (64, 48))


def test_video_command_reports_a_log_without_frames_in_one_line(tmp_path):
    path = tmp_path / "bare.mcap"
    write_trial(path, make_trial(seed=6))
    result = CliRunner().invoke(app, ["video", str(path)])
    assert result.exit_code == 2 and "no camera frames" in result.output
