"""The OAK camera's configuration: validated, and building the live or the replay driver."""

from pathlib import Path

import pytest
from pydantic import ValidationError

from configuration.devices import OakCameraConfig
from drivers.oak import OakCamera, OakReplay


def test_oak_camera_config_builds_the_live_driver():
    config = OakCameraConfig(width=640, height=400, fps=15, channels=1, exposure_us=8000)
    camera = config.build()
    assert isinstance(camera, OakCamera)
    assert (camera.width, camera.height, camera.fps, camera.channels) == (640, 400, 15.0, 1)
    assert (camera.exposure_us, camera.iso, camera.socket) == (8000, 400, "CAM_A")


def test_oak_camera_config_builds_the_replay_driver():
    config = OakCameraConfig.model_validate(
        {"channels": 1, "replay": {"video": "r/video.avi", "calibration": "r/calibration.json"}}
    )
    replay = config.build()
    assert isinstance(replay, OakReplay) and replay.realtime and replay.channels == 1
    assert replay.video == Path("r/video.avi") and replay.calibration == Path("r/calibration.json")


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"socket": "CAM_Z"}, "socket"),
        ({"fps": 0}, "fps"),
        ({"iso": 50}, "iso"),
        ({"exposure": 100}, "exposure"),  # the field is exposure_us
        ({"replay": {"video": "v.avi"}}, "calibration"),
    ],
)
def test_oak_camera_config_rejects_bad_fields(fields, message):
    with pytest.raises(ValidationError, match=message):
        OakCameraConfig.model_validate(fields)
