import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from configuration.camera import load_camera
from hil.cli import app
from hil.evaluation.scenarios import camera_pose_for, target_offset

runner = CliRunner()


def test_version_and_help():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.startswith("satgrasp ")
    for command in ([], ["render"], ["bench", "render"], ["demo"]):
        result = runner.invoke(app, [*command, "--help"])
        assert result.exit_code == 0, result.output
        assert "Usage" in result.output


def test_render_writes_frame_and_truth(tmp_path):
    out, truth = tmp_path / "f.png", tmp_path / "t.json"
    args = [
        "render",
        "--camera",
        "reference",
        "--distance",
        "2.0",
        "--dx",
        "0.05",
        "--yaw-deg",
        "10",
        "--noise",
        "low",
        "--seed",
        "1",
        "--out",
        str(out),
        "--truth",
        str(truth),
    ]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "X_CT" in result.output
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert image.shape == (480, 640) and image.dtype == np.uint8
    record = json.loads(truth.read_text())
    _, X_CT = camera_pose_for(2.0, target_offset(dx=0.05, yaw=np.radians(10)))
    assert np.allclose(record["X_CT"], X_CT.matrix, atol=1e-12)
    assert np.allclose(record["camera"]["K"], load_camera("reference").camera_info().K)
    assert record["camera"]["width"] == 640 and record["camera"]["dist"] == []
    # Same seed → identical frame.
    again = tmp_path / "g.png"
    runner.invoke(app, [*args[:-4], "--out", str(again)])
    assert np.array_equal(cv2.imread(str(again), cv2.IMREAD_UNCHANGED), image)


def test_render_colour_camera_with_distortion(tmp_path):
    out = tmp_path / "oak.png"
    result = runner.invoke(
        app, ["render", "--camera", "oak_d_rgb", "--distance", "3", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert cv2.imread(str(out)).shape == (800, 1280, 3)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--camera", "nikon"], "no built-in configuration named 'nikon'"),
        (["--noise", "medium"], "Invalid value for '--noise': 'medium' is not one of"),
        (["--distance", "-1"], "--distance must be positive"),
        (["--distance", "0.3", "--dz", "0.5"], "behind the camera"),
    ],
)
def test_render_rejects_bad_options(tmp_path, args, message):
    result = runner.invoke(app, ["render", "--out", str(tmp_path / "x.png"), *args])
    assert result.exit_code == 2
    assert message in result.output.replace("\n", " ")


def test_console_script_runs_from_another_directory(tmp_path):
    exe = [sys.executable, "-c", "from hil.cli import main; main()"]
    result = subprocess.run(
        [*exe, "render", "--out", "f.png"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "f.png").is_file()
    assert "pybullet build time" not in result.stdout + result.stderr


def test_estimate_reports_unreadable_images_as_lost(tmp_path):
    result = runner.invoke(
        app,
        [
            "estimate",
            "--system",
            "tests.hil.fake_estimators:build_raising",
            str(tmp_path / "missing.png"),
        ],
    )
    assert result.exit_code == 0, result.output
    record = json.loads(result.output.strip().splitlines()[-1])
    assert record["status"] == "lost" and "cannot read image" in record["reason"]


def test_estimate_rejects_an_unknown_system(tmp_path):
    result = runner.invoke(app, ["estimate", "--system", "sonar", str(tmp_path / "x.png")])
    assert result.exit_code == 2 and "unknown estimator system" in result.output


def test_bench_estimate_times_a_plugged_in_estimator():
    result = runner.invoke(
        app,
        [
            "bench",
            "estimate",
            "--system",
            "tests.hil.fake_estimators:build_blind",
            "--frames",
            "2",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "acquisition" in result.output and "0/2" in result.output


def test_campaign_runs_the_seeds_asked_for_and_writes_a_summary(tmp_path):
    camera = tmp_path / "small_camera.yaml"
    camera.write_text("name: small\nwidth: 160\nheight: 120\nhfov_deg: 70\n")
    config = tmp_path / "sim.yaml"
    config.write_text(
        f"name: campaign-test\ncamera: {camera}\n"
        "systems: [tests.hil.fake_estimators:build_oracle]\nvision: {log_frames_every_s: 0}\n"
    )
    out_dir = tmp_path / "campaign"
    args = ["campaign", "--config", str(config), "--seeds", "1", "--first-seed", "7"]
    result = runner.invoke(app, [*args, "--noise", "none", "--out-dir", str(out_dir)])
    assert result.exit_code == 0, result.output
    assert "1 trials run, 0 already done" in result.output
    assert "[1/1] approach/none-s7-" in result.output  # no terminal: a line per trial, not a bar
    logs = sorted(p.relative_to(out_dir).as_posix() for p in out_dir.rglob("*.mcap"))
    assert len(logs) == 1 and logs[0].startswith("logs/approach/none-s7-"), logs
    summary = (out_dir / "summary.md").read_text()
    assert "| none | 1 | 1/1 (100 %)" in summary


def test_bench_estimate_json_parses():
    args = ["bench", "estimate", "--system", "ellipses", "--frames", "1", "--distance", "2"]
    result = runner.invoke(app, [*args, "--json"])
    assert result.exit_code == 0, result.output
    document = json.loads(result.stdout)
    (row,) = document["rows"]
    assert row["system"] == "ellipses" and row["distance_m"] == 2.0 and row["frames"] == 1
    assert {"tracking_median_ms", "opencv_median_ms", "time_ratio"} <= row.keys()


def test_approach_rejects_an_unknown_light_before_anything_starts(tmp_path):
    result = runner.invoke(app, ["approach", "--light", "dusk", "--log-dir", str(tmp_path)])
    assert result.exit_code == 2
    assert "--light: light must be one of default, harsh, random" in " ".join(result.output.split())
    assert not list(tmp_path.iterdir())  # no trial log: nothing ran
