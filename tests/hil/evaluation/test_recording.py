"""`satgrasp record` and the replay check: a simulated approach recorded as video + depthai
calibration JSON + ground truth, replayed through the OAK driver (depthai's ReplayVideo, no
device) and tracked by the estimators — poses within the accuracy bounds of the recorded truth,
and as the direct (never encoded) frames give them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from drivers.oak import board_socket, read_calibration
from hil.cli import app
from hil.evaluation.recording import Recording, record_and_check, replay_timing

#: How far a replayed pose may be from the direct frame's. FFV1 replays the pixels exactly; what
#: remains is K rounded to float32 by depthai's calibration format (< 1e-5 px), which the
#: ellipse system's iterations can amplify to ~0.3 mm on a frame (measured; docs/oak.md).
REPLAY_TOLERANCE = (0.001, math.radians(0.1))


def _check_rows(result, min_valid: dict[str, int]) -> None:
    for row in result.comparison:
        assert row.valid_replayed == row.valid_direct >= min_valid[row.system], row
        assert row.within_bounds == row.valid_replayed, row  # every pose within 3× target
        assert row.difference[0] <= REPLAY_TOLERANCE[0], row
        assert row.difference[1] <= REPLAY_TOLERANCE[1], row


def test_replayed_approach_matches_the_truth_and_the_direct_frames(tmp_path):
    result = record_and_check(tmp_path / "rec", frames=8, noise="low", seed=1)
    recording = Recording.load(tmp_path / "rec")
    assert recording == result.recording and recording.codec == "ffv1"
    truth = recording.read_truth()
    assert [t.seq for t in truth] == list(range(8)) == result.replay.seqs
    assert truth[0].distance_m == 2.5 and truth[-1].distance_m == 0.5
    assert np.allclose([t.stamp for t in truth], np.arange(8) / 30.0)
    # Corners and lines lose the panel in the last metre (it leaves the view); the ring stays.
    _check_rows(result, {"corners": 5, "lines": 5, "ellipses": 8})
    statuses = {
        system: [m.status for m in measurements.values()]
        for system, measurements in result.replay.measurements.items()
    }
    assert statuses == {
        system: [m.status for m in measurements.values()]
        for system, measurements in result.direct.items()
    }
    timing = replay_timing(recording)  # paced at the recorded 30 fps, newest frame only
    # 33 ms (whole milliseconds): the replay wakes once per period, then decodes and sends (the
    # send stamps), so single periods vary with the decoding time (29 ms medians seen with 2
    # busy cores).
    assert timing.frames >= 7 and 0.025 < timing.period_median_s < 0.06
    assert timing.latency_median_s < 0.05 and timing.unpaced_frame_s < 0.1
    # A busy machine may pass up one frame (newest frame only), as the bound above allows.
    assert f"replay paced at 30 fps: {timing.frames} frames" in timing.text()


def test_a_14_coefficient_calibration_works_end_to_end(tmp_path):
    """A camera with depthai's full distortion model (rational, thin prism, tilted sensor):
    rendered, recorded, its calibration written and read back by depthai, replayed, tracked."""
    profile = tmp_path / "oak14.yaml"
    profile.write_text(
        "name: oak14\nwidth: 640\nheight: 400\nfx: 466.0\nfy: 465.5\ncx: 320.6\ncy: 199.3\n"
        "distortion: [-0.09, 0.11, 0.0003, -0.0004, -0.04, 0.02, -0.01, 0.005,"
        " 0.001, -0.0005, 0.002, -0.001, 0.004, -0.003]\nchannels: 3\nfps: 30\n"
    )
    result = record_and_check(
        tmp_path / "rec", ("ellipses",), frames=4, camera=str(profile), seed=2
    )
    calibration = read_calibration(result.recording.calibration)
    assert len(calibration.getDistortionCoefficients(board_socket("CAM_A"))) == 14
    assert result.replay.seqs == [0, 1, 2, 3]
    _check_rows(result, {"ellipses": 4})


def test_record_command_writes_a_recording_and_rejects_bad_options(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["record", "--out", str(tmp_path / "r"), "--frames", "2"])
    assert result.exit_code == 0, result.output
    recording = Recording.load(tmp_path / "r")
    assert recording.frames == 2 and recording.video.stat().st_size > 0
    assert len(recording.read_truth()) == 2
    args = ["record", "--out", str(tmp_path / "m"), "--frames", "2", "--codec", "mjpg"]
    assert runner.invoke(app, args).exit_code == 0
    with Recording.load(tmp_path / "r").replay() as lossless:
        exact = [lossless.read(timeout_s=5.0).image for _ in range(2)]
    with Recording.load(tmp_path / "m").replay() as jpeg:
        lossy = [jpeg.read(timeout_s=5.0).image for _ in range(2)]
    for a, b in zip(exact, lossy, strict=True):  # the same rendered frame, JPEG at quality 100
        error = np.abs(a.astype(float) - b)
        assert 0 < error.mean() < 2.0
    result = runner.invoke(app, ["record", "--out", str(tmp_path / "x"), "--codec", "h264"])
    assert result.exit_code == 2
    assert "'h264' is not one of 'ffv1', 'mjpg'" in result.output
    with pytest.raises(ValueError, match="not a recording"):
        Recording.load(tmp_path)
