"""OAK cameras on depthai v3: a live camera (``OakCamera``) and the replay of a recorded video
with its calibration (``OakReplay``, a host-only pipeline: no device). Both implement
``drivers.base.Camera`` and turn depthai's ``ImgFrame`` into the same ``Frame``s:

* the image as depthai delivers it (GRAY8 → HxW, BGR888i → HxWx3, OpenCV's BGR order);
* ``stamp`` = the middle of the exposure on the host's steady clock
  (``ImgFrame.getTimestamp(CameraExposureOffset.MIDDLE)``; depthai's host clock is
  ``std::chrono::steady_clock``, which is ``time.monotonic()`` on Linux), ``exposure_s`` from
  the frame, ``arrival_stamp`` = when ``read`` took it (so ``Frame.latency_s`` is measured);
* ``info`` = the calibration's intrinsics scaled to the output size and its distortion (depthai
  reports OpenCV's 14 coefficients), one ``CameraInfo`` object for the whole stream.

Newest frame only: the live output queue holds one frame and never blocks the device, so a
frame that waited is replaced by a newer one and never acted on. A replay paced at the recorded
rate reads through the same kind of queue; ``realtime=False`` instead delivers every frame, in
order, as fast as the reader asks (tests, batch evaluation).
"""

from __future__ import annotations

import datetime
import json
import time
from pathlib import Path

import cv2
import depthai as dai
import numpy as np

from drivers.base import DeviceError, DeviceTimeout
from estimators.frame import CameraInfo, Frame
from estimators.geometry import padded_distortion

#: Socket names a configuration may use (the OAK's colour camera is CAM_A).
SOCKETS = tuple(f"CAM_{letter}" for letter in "ABCDEFGH")


class ReplayFinished(DeviceError):
    """A replay has delivered its last frame; no more will come."""


def board_socket(name: str) -> dai.CameraBoardSocket:
    """depthai's socket for a name such as ``"CAM_A"``."""
    if name not in SOCKETS:
        raise ValueError(f"camera socket must be one of {', '.join(SOCKETS)}; got {name!r}")
    return getattr(dai.CameraBoardSocket, name)


def _frame_type(channels: int) -> dai.ImgFrame.Type:
    return dai.ImgFrame.Type.GRAY8 if channels == 1 else dai.ImgFrame.Type.BGR888i


# --- calibration ----------------------------------------------------------------------------


def read_calibration(path: Path) -> dai.CalibrationHandler:
    """depthai's calibration from a JSON file (as ``eepromToJsonFile`` writes it)."""
    path = Path(path)
    if not path.is_file():
        raise DeviceError(f"calibration {path}: no such file")
    try:
        json.loads(path.read_text(encoding="utf-8"))
        return dai.CalibrationHandler(str(path))
    except (RuntimeError, ValueError, UnicodeDecodeError) as exc:
        first_line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DeviceError(f"calibration {path}: not a depthai calibration ({first_line})") from None


def camera_info_from_calibration(
    calibration: dai.CalibrationHandler,
    socket: str,
    width: int,
    height: int,
    *,
    channels: int,
    model: str,
    source: str = "calibration",
) -> CameraInfo:
    """The ``CameraInfo`` of ``socket``'s output at ``width``×``height``.

    K is depthai's ``getCameraIntrinsics(socket, width, height)``: the calibrated matrix scaled
    to the output (keeping the aspect ratio and cropping the rest, as the camera's CROP resize
    mode does). The distortion is the calibration's as is (OpenCV order, 14 coefficients from a
    device; a shorter list is zero-padded to the next length OpenCV knows). ``source`` names the
    calibration in errors.
    """
    dai_socket = board_socket(socket)
    if not calibration.hasCameraCalibration(dai_socket):
        raise DeviceError(f"{source} has no intrinsics for socket {socket}")
    model_type = calibration.getDistortionModel(dai_socket)
    if model_type != dai.CameraModel.Perspective:
        raise DeviceError(
            f"{source}: socket {socket} is calibrated with the {model_type.name} model; "
            "only the perspective (OpenCV) model is supported"
        )
    K = np.array(calibration.getCameraIntrinsics(dai_socket, width, height), dtype=float)
    dist = np.array(calibration.getDistortionCoefficients(dai_socket), dtype=float)
    if np.all(dist == 0):
        dist = np.zeros(0)  # so that nothing downstream runs the distortion model for nothing
    try:
        dist = padded_distortion(dist)
    except ValueError as exc:
        raise DeviceError(f"{source}: socket {socket}: {exc}") from None
    return CameraInfo(width, height, K, dist, model, channels)


def calibration_of(info: CameraInfo, socket: str = "CAM_A") -> dai.CalibrationHandler:
    """A depthai calibration holding ``info``'s intrinsics and distortion at its size for
    ``socket`` (perspective model). depthai stores them in float32."""
    dai_socket = board_socket(socket)
    calibration = dai.CalibrationHandler()
    calibration.setCameraIntrinsics(dai_socket, info.K.tolist(), info.width, info.height)
    calibration.setDistortionCoefficients(dai_socket, info.dist.tolist())
    calibration.setCameraType(dai_socket, dai.CameraModel.Perspective)
    return calibration


def write_calibration(info: CameraInfo, path: Path, socket: str = "CAM_A") -> None:
    """Write ``info`` as a depthai calibration JSON (``eepromToJsonFile``), readable by
    ``dai.CalibrationHandler(path)`` and ``read_calibration``."""
    if not calibration_of(info, socket).eepromToJsonFile(str(path)):
        raise DeviceError(f"calibration {path}: depthai could not write it")


# --- frames ---------------------------------------------------------------------------------


def _to_frame(message: dai.ImgFrame, info: CameraInfo, seq: int) -> Frame:
    arrival = time.monotonic()
    image = message.getCvFrame()
    return Frame(
        image=image,
        stamp=message.getTimestamp(dai.CameraExposureOffset.MIDDLE).total_seconds(),
        info=info,
        seq=seq,
        exposure_s=message.getExposureTime().total_seconds(),
        arrival_stamp=arrival,
    )


def _take(queue: dai.MessageQueue, timeout_s: float, what: str) -> dai.ImgFrame:
    """The next message of ``queue`` within ``timeout_s``, or DeviceTimeout/DeviceError."""
    try:
        message = queue.get(datetime.timedelta(seconds=max(timeout_s, 0.0)))
    except RuntimeError as exc:  # dai.MessageQueue.QueueException: the pipeline stopped
        raise DeviceError(f"{what}: the pipeline stopped ({exc})") from None
    if message is None:
        raise DeviceTimeout(f"{what}: no frame within {timeout_s:.3f} s")
    return message


class _Stream:
    """The lifecycle both cameras share: a pipeline that streams while active. Subclasses
    define ``connect``, ``activate``, ``close`` and ``read``."""

    _what = "OAK"

    def __init__(self) -> None:
        self._info: CameraInfo | None = None
        self._pipeline: dai.Pipeline | None = None
        self._queue: dai.MessageQueue | None = None
        self._expected_seq: int | None = None
        #: Frames the device sent that were replaced by newer ones before ``read`` took them.
        self.dropped = 0

    @property
    def info(self) -> CameraInfo:
        if self._info is None:
            raise DeviceError(f"{self._what}: not connected (call connect())")
        return self._info

    @property
    def active(self) -> bool:
        return self._pipeline is not None

    def _start(self, pipeline: dai.Pipeline, queue: dai.MessageQueue) -> None:
        try:
            pipeline.start()
        except RuntimeError as exc:
            raise DeviceError(f"{self._what}: the pipeline did not start ({exc})") from None
        self._pipeline, self._queue = pipeline, queue
        self._expected_seq = None

    def deactivate(self) -> None:
        pipeline, self._pipeline, self._queue = self._pipeline, None, None
        if pipeline is not None:
            pipeline.stop()
            pipeline.wait()

    def __enter__(self):
        """``with camera:`` connects, activates, and closes at the end."""
        self.connect()
        try:
            self.activate()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _message(self, timeout_s: float) -> dai.ImgFrame:
        if self._queue is None:
            raise DeviceError(f"{self._what}: not streaming (call activate())")
        return _take(self._queue, timeout_s, self._what)

    def _deliver(self, message: dai.ImgFrame) -> Frame:
        """The frame of ``message``; a gap in the sequence numbers counts as dropped frames."""
        seq = message.getSequenceNum()
        if self._expected_seq is not None and seq > self._expected_seq:
            self.dropped += seq - self._expected_seq
        self._expected_seq = seq + 1
        return _to_frame(message, self.info, seq)


# --- live camera ----------------------------------------------------------------------------


class OakCamera(_Stream):
    """A live OAK camera: ``socket``'s output at ``width``×``height`` and ``fps``, optional
    manual exposure (µs, ISO), intrinsics from the device's own calibration.

    ``device`` selects one OAK by its id, name or IP (None: the first one found). ``connect``
    looks for it first (a quick scan) so that a missing camera fails at once instead of after
    depthai's own search time-out.
    """

    def __init__(
        self,
        *,
        socket: str = "CAM_A",
        width: int = 1280,
        height: int = 800,
        fps: float = 30.0,
        channels: int = 3,
        exposure_us: int | None = None,
        iso: int = 400,
        device: str | None = None,
    ):
        super().__init__()
        board_socket(socket)
        self.socket, self.width, self.height, self.fps = socket, width, height, fps
        self.channels, self.exposure_us, self.iso, self.device_id = (
            channels,
            exposure_us,
            iso,
            device,
        )
        self._device: dai.Device | None = None
        self._what = f"OAK {device or ''} {socket}".replace("  ", " ")

    def connect(self) -> None:
        if self._device is not None:
            return
        found = dai.Device.getAllAvailableDevices()
        if self.device_id is not None:
            found = [d for d in found if self.device_id in (d.getDeviceId(), d.name)]
        if not found:
            which = f" {self.device_id!r}" if self.device_id else ""
            raise DeviceError(f"no OAK device{which} found (USB or network)")
        try:
            device = dai.Device(found[0])
        except RuntimeError as exc:
            raise DeviceError(f"{self._what}: cannot open the device ({exc})") from None
        try:
            self._info = camera_info_from_calibration(
                device.readCalibration(),
                self.socket,
                self.width,
                self.height,
                channels=self.channels,
                model=f"oak:{device.getDeviceId()}:{self.socket}",
                source=f"the calibration of OAK {device.getDeviceId()}",
            )
        except Exception:
            device.close()
            raise
        self._device = device

    def activate(self) -> None:
        if self._device is None:
            raise DeviceError(f"{self._what}: not connected (call connect())")
        if self.active:
            return
        pipeline = dai.Pipeline(self._device)
        camera = pipeline.create(dai.node.Camera).build(
            board_socket(self.socket), sensorFps=self.fps
        )
        if self.exposure_us is not None:
            camera.initialControl.setManualExposure(self.exposure_us, self.iso)
        output = camera.requestOutput(
            (self.width, self.height),
            type=_frame_type(self.channels),
            resizeMode=dai.ImgResizeMode.CROP,  # as getCameraIntrinsics scales K
            fps=self.fps,
            enableUndistortion=False,  # the estimators undistort with the calibration
        )
        self._start(pipeline, output.createOutputQueue(maxSize=1, blocking=False))

    def close(self) -> None:
        self.deactivate()
        device, self._device = self._device, None
        if device is not None:
            device.close()

    def read(self, timeout_s: float = 1.0) -> Frame:
        return self._deliver(self._message(timeout_s))


# --- replay ---------------------------------------------------------------------------------


class OakReplay(_Stream):
    """A recorded video replayed through depthai's ``ReplayVideo`` with its calibration JSON.

    ``realtime`` (default) paces the replay at ``fps`` (None: the video's own rate) on the host
    clock, and, like the live camera, keeps only the newest frame; ``realtime=False`` delivers
    every frame in order as fast as ``read`` is called. ``channels`` 1 replays mono (GRAY8),
    3 colour (BGR888i). After the last frame ``read`` raises ``ReplayFinished``.

    The video must have the calibration's image size, or the same aspect ratio (the intrinsics
    are then scaled); a lossless codec (FFV1) replays the recorded pixels exactly.
    """

    #: The replay node's rate when not paced: it sleeps ⌈1000/fps⌉ ms between frames.
    _UNPACED_FPS = 1000.0

    def __init__(
        self,
        video: Path,
        calibration: Path,
        *,
        socket: str = "CAM_A",
        channels: int = 1,
        fps: float | None = None,
        realtime: bool = True,
    ):
        super().__init__()
        board_socket(socket)
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3; got {channels}")
        self.video, self.calibration = Path(video), Path(calibration)
        self.socket, self.channels, self.realtime = socket, channels, realtime
        self._fps_asked = fps
        self.fps = 0.0
        self.frame_count = 0
        self._what = f"replay {self.video.name}"

    def connect(self) -> None:
        if not self.video.is_file():
            raise DeviceError(f"replay video {self.video}: no such file")
        calibration = read_calibration(self.calibration)
        capture = cv2.VideoCapture(str(self.video))
        try:
            if not capture.isOpened():
                raise DeviceError(f"replay video {self.video}: cannot be decoded")
            width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
            height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
            frames = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            video_fps = float(capture.get(cv2.CAP_PROP_FPS))
        finally:
            capture.release()
        if frames <= 0 or width <= 0 or height <= 0:
            raise DeviceError(f"replay video {self.video}: no frames")
        fps = self._fps_asked or video_fps
        if not fps > 0:
            raise DeviceError(f"replay video {self.video}: no frame rate (give fps)")
        dai_socket = board_socket(self.socket)
        if calibration.hasCameraCalibration(dai_socket):
            _, cal_width, cal_height = calibration.getDefaultIntrinsics(dai_socket)
            if abs(width * cal_height - height * cal_width) > 0.002 * cal_width * cal_height:
                raise DeviceError(
                    f"replay video {self.video} is {width}x{height} but calibration "
                    f"{self.calibration} is for {cal_width}x{cal_height} (another aspect ratio)"
                )
        self._info = camera_info_from_calibration(
            calibration,
            self.socket,
            width,
            height,
            channels=self.channels,
            model=f"replay:{self.video.name}",
            source=f"calibration {self.calibration}",
        )
        self.fps, self.frame_count = fps, frames

    def activate(self) -> None:
        if self._info is None:
            raise DeviceError(f"{self._what}: not connected (call connect())")
        if self.active:
            return
        pipeline = dai.Pipeline(False)  # host only: no device
        replay = pipeline.create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(self.video)
        replay.setOutFrameType(_frame_type(self.channels))
        # Looping keeps the pipeline up after the last frame (a finished replay stops the
        # pipeline and closes its queue, which can drop the last frame); the sequence number
        # runs on, so frames past the count are the second loop and are not delivered.
        replay.setLoop(True)
        replay.setFps(self.fps if self.realtime else self._UNPACED_FPS)
        if self.realtime:
            queue = replay.out.createOutputQueue(maxSize=1, blocking=False)
        else:
            queue = replay.out.createOutputQueue(maxSize=2, blocking=True)
        self._start(pipeline, queue)
        self._expected_seq = 0  # the replay starts at its first frame

    def close(self) -> None:
        self.deactivate()

    def read(self, timeout_s: float = 1.0) -> Frame:
        finished = ReplayFinished(f"{self._what}: all {self.frame_count} frames replayed")
        if self._expected_seq is not None and self._expected_seq >= self.frame_count:
            raise finished
        message = self._message(timeout_s)
        if message.getSequenceNum() >= self.frame_count:  # the replay's second loop
            self._expected_seq = self.frame_count
            raise finished
        return self._deliver(message)
