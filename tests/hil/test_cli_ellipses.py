"""``satgrasp estimate --system ellipses`` on rendered frames: JSON lines with the 5-DOF circle
pose (and X_CT with the thruster), tracking across images, overlays."""

import json
import math

import cv2
import numpy as np
from typer.testing import CliRunner

from hil.cli import app

runner = CliRunner()


def test_estimate_ellipses_on_rendered_frames(tmp_path):
    images = []
    for k, (distance, yaw) in enumerate(((2.0, 0.0), (1.9, 2.0))):
        out, truth = tmp_path / f"f{k}.png", tmp_path / f"t{k}.json"
        result = runner.invoke(
            app,
            [
                "render",
                "--distance",
                str(distance),
                "--dx",
                "0.04",
                "--yaw-deg",
                str(yaw),
                "--noise",
                "low",
                "--seed",
                str(k),
                "--out",
                str(out),
                "--truth",
                str(truth),
            ],
        )
        assert result.exit_code == 0, result.output
        images.append((out, json.loads(truth.read_text())))
    overlay = tmp_path / "overlay"
    result = runner.invoke(
        app,
        ["estimate", "--system", "ellipses", "--track", "--overlay", str(overlay)]
        + [str(path) for path, _ in images],
    )
    assert result.exit_code == 0, result.output
    lines = [json.loads(line) for line in result.output.strip().splitlines()]
    assert [line["status"] for line in lines] == ["acquired", "tracking"]
    for line, (_, truth) in zip(lines, images, strict=True):
        X_true = np.array(truth["X_CT"])
        assert line["circle"] == "ring_outer"
        assert np.linalg.norm(np.array(line["center_C"]) - X_true[:3, 3]) < 0.01
        n_true = X_true[:3, 2]  # the ring's normal is T's z axis
        angle = math.degrees(math.acos(np.clip(np.dot(line["normal_C"], n_true), -1, 1)))
        assert angle < 3.0
        assert np.array(line["covariance_5dof"]).shape == (5, 5)
        assert line["X_CT"] is not None and np.array(line["covariance"]).shape == (6, 6)
        assert np.linalg.norm(np.array(line["X_CT"])[:3, 3] - X_true[:3, 3]) < 0.01
    drawn = cv2.imread(str(overlay / "f0_ellipses.png"))
    assert drawn is not None and drawn.shape == (480, 640, 3)


def test_estimate_ellipses_reports_lost_for_a_blank_image(tmp_path):
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 90, np.uint8))
    result = runner.invoke(app, ["estimate", "--system", "ellipses", str(blank)])
    assert result.exit_code == 0, result.output
    line = json.loads(result.output.strip())
    assert line["status"] == "lost" and "no contrast (uniform" in line["reason"]
    assert line["center_C"] is None and line["X_CT"] is None
