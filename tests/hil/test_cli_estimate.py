"""`satgrasp estimate` with the corner and line systems on rendered images."""

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from estimators.geometry import Pose, translation_error
from hil.cli import app
from tests.estimators import rendered

runner = CliRunner()


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Two low-noise frames of the default mock-up at 1.2 m, as PNG files, with their truth."""
    folder = tmp_path_factory.mktemp("frames")
    paths, truths = [], []
    for seq in range(2):
        f = rendered.frame(1.2, seed=seq, seq=seq)
        path = folder / f"frame{seq}.png"
        cv2.imwrite(str(path), f.image)
        paths.append(path)
        truths.append(f.truth.X_CT)
    return paths, truths


@pytest.mark.parametrize("system", ["corners", "lines"])
def test_estimate_prints_one_json_line_per_image_and_draws_overlays(images, tmp_path, system):
    paths, truths = images
    overlay = tmp_path / "overlay"
    args = ["estimate", "--system", system, "--track", "--overlay", str(overlay)]
    result = runner.invoke(app, [*args, *map(str, paths)])
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in result.output.strip().splitlines()]
    assert [r["status"] for r in records] == ["acquired", "tracking"]
    for record, path, X_true in zip(records, paths, truths, strict=True):
        assert record["image"] == str(path) and record["system"] == system
        assert record["reason"] == "" and record["time_ms"] > 0
        X_CT = Pose.from_matrix(np.array(record["X_CT"]), orthonormalize=True)
        assert translation_error(X_true, X_CT) < 0.01
        assert np.array(record["covariance"]).shape == (6, 6)
        assert 0 < record["residual_px"] < 2
        drawn = cv2.imread(str(overlay / f"{path.stem}_{system}.png"))
        assert drawn is not None and drawn.shape[:2] == (480, 640)
        assert np.any(drawn[:, :, 2] != drawn[:, :, 0])  # coloured marks on the grey frame
