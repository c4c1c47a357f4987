"""The simulated rig as one world: arm, track carrying the mock-up, gripper, scene and camera,
all on one simulated clock and advanced together (``advance``) between control ticks.

The camera streams like a real one: the world triggers a capture at the frame rate (the image
shows the scene at that instant) and the frame reaches the host ``timing.latency_s`` ±
``jitter_s`` later (``sim_backends.camera.StreamingSimCamera``).

The loop reaches these devices only through their protocols and real drivers: the track and
the gripper are driven by ``ModbusTrack`` and ``RobotiqGripper`` over their register maps —
in-process (``links="direct"``, fast) or over a real pymodbus TCP server on loopback
(``links="tcp"``, the full protocol path).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Mapping
from typing import Literal

import numpy as np

from configuration.camera import CameraConfig
from configuration.mockup import MockupConfig
from configuration.render import NoiseConfig, RenderConfig
from configuration.rig import RigConfig
from configuration.vision import CameraTiming
from drivers.clock import SimClock
from drivers.gripper_robotiq import RobotiqGripper
from drivers.track_modbus import ModbusTrack
from estimators.geometry import Pose, rotation_error_geodesic, translation_error
from sim_backends.arm import SimArm
from sim_backends.camera import SimCamera, StreamingSimCamera, Viewpoint
from sim_backends.gripper import GripperModel
from sim_backends.modbus_server import DirectLink, ModbusDeviceServer
from sim_backends.renderer import make_renderer
from sim_backends.scene import MockupScene
from sim_backends.track import TrackModel


class SimRig:
    """The simulated devices of the rig — arm, track carrying the mock-up, gripper — on one
    clock, advanced together, with the camera's capture instants at the frame rate.

    ``grasp_X_TC``: where the camera is when the fingers straddle the ring lip; within
    ``capture_position_m`` / ``capture_angle_deg`` of it (a compliant gripper's capture range)
    the world puts an object of ``object_width`` between the fingers. Contact: the fingertips
    reach ``tool_reach_m`` ahead of the camera along its optical axis; pushed past the ring's
    face plane (z_T = 0) by δ they feel ``contact_stiffness``·δ along the face normal, which the
    arm reports as its TCP wrench (None: no contact model). ``on_capture(stamp)`` is
    called at every frame instant once ``start`` has run (``SimWorld`` renders there; the
    wall-clock world process asks its camera process to).
    """

    def __init__(
        self,
        rig: RigConfig,
        *,
        grasp_X_TC: Pose,
        start_q: np.ndarray | None = None,
        links: Literal["direct", "tcp"] = "direct",
        capture_position_m: float = 0.01,
        capture_angle_deg: float = 3.0,
        object_width: float = 0.05,
        timing: CameraTiming | None = None,
        start_time: float = 0.0,
        tool_reach_m: float | None = None,
        contact_stiffness: float = 2000.0,
    ):
        self.clock = SimClock(start_time)
        self.timing = timing or CameraTiming()
        self._next_capture = math.inf
        self.rig = rig
        self._grasp_X_TC = grasp_X_TC
        self._capture_m = capture_position_m
        self._capture_rad = math.radians(capture_angle_deg)
        self._object_width = object_width
        self._tool_reach_m = tool_reach_m
        self._contact_stiffness = contact_stiffness
        self._servers: list[ModbusDeviceServer] = []
        try:
            self.arm = SimArm(rig.arm, clock=self.clock.now)
            if start_q is not None:
                self.arm.set_joint_positions(np.asarray(start_q, dtype=float))
            self.track_model = TrackModel(rig.track)
            self.gripper_model = GripperModel(rig.gripper)
            self.track, self.gripper = self._drivers(links)
        except Exception:
            self.close()
            raise

    @property
    def grid_s(self) -> float:
        """The world's time step: the shortest time after which every device model has finished
        a whole number of its control periods (arm 2 ms, track 4 ms → 4 ms). At a multiple of it
        every model's state is the state *of that instant*; in between, a model is up to one of its
        periods behind the clock, which at 0.25 m/s is a millimetre — so frames are captured, and
        the wall-clock world advances, on this grid."""
        periods_us = [
            round(1e6 / rate)
            for rate in (
                self.rig.arm.control_rate_hz,
                self.rig.track.control_rate_hz,
                self.gripper_model.control_rate_hz,
            )
        ]
        return math.lcm(*periods_us) / 1e6

    def on_capture(self, stamp: float) -> None:
        """A frame instant (nothing to do without a camera)."""

    def _drivers(self, links: str) -> tuple[ModbusTrack, RobotiqGripper]:
        track_cfg, gripper_cfg = self.rig.track.modbus, self.rig.gripper.modbus
        speed, force = self.rig.gripper.grip_speed, self.rig.gripper.grip_force
        if links == "direct":
            track = ModbusTrack(
                DirectLink(self.track_model, "simulated track"), clock=self.clock.now
            )
            gripper = RobotiqGripper(
                DirectLink(self.gripper_model, "simulated gripper"),
                speed=speed,
                force=force,
                clock=self.clock.now,
            )
            return track, gripper
        if links != "tcp":
            raise ValueError(f"links must be 'direct' or 'tcp'; got {links!r}")
        for devices in (
            {track_cfg.device_id: self.track_model},
            {gripper_cfg.device_id: self.gripper_model},
        ):
            self._servers.append(ModbusDeviceServer(devices, host="127.0.0.1", port=0).start())
        track = ModbusTrack.over_tcp(
            "127.0.0.1",
            self._servers[0].port,
            track_cfg.device_id,
            timeout_s=track_cfg.timeout_s,
            clock=self.clock.now,
        )
        gripper = RobotiqGripper.over_tcp(
            "127.0.0.1",
            self._servers[1].port,
            gripper_cfg.device_id,
            timeout_s=gripper_cfg.timeout_s,
            speed=speed,
            force=force,
            clock=self.clock.now,
        )
        return track, gripper

    def silence_track(self) -> None:
        """Fault injection: the track's Modbus device stops answering (in-process: every
        request times out; over TCP: its server goes away). Its own watchdog then stops it."""
        link = self.track.link
        if isinstance(link, DirectLink):
            link.drop()
        else:
            self._servers[0].stop()

    # --- what the camera sees -------------------------------------------------------------
    def viewpoint(self) -> Viewpoint:
        """The camera's pose and its twist relative to the target (for motion blur), now."""
        X_WC = self.arm.camera_pose_W()
        # Relative twist for motion blur: the camera's own, minus the carriage's motion seen in C.
        twist = np.array(self.arm.camera_twist_C(), dtype=float)
        carriage_v_W = self.track_model.velocity * self.rig.track.axis_unit_W
        twist[:3] -= X_WC.R.T @ carriage_v_W
        return Viewpoint(X_WC, twist)

    def devices(self) -> tuple:
        return (self.arm, self.track, self.gripper)

    # --- stepping -------------------------------------------------------------------------
    def start(self, settle_s: float = 1.0, dt: float = 0.01) -> None:
        """Connect and activate every device, the gripper's activation completed (advancing
        simulated time); frames are captured from then on."""
        for device in self.devices():
            device.connect()
        for device in reversed(self.devices()):
            device.activate()
        waited = 0.0
        grid = self.grid_s
        dt = max(grid, round(dt / grid) * grid)
        while not self.gripper.state().activated:
            if waited > settle_s + self.rig.gripper.activation_s:
                raise RuntimeError("the simulated gripper did not activate")
            self.advance(dt)
            waited += dt
        self._next_capture = self.clock.now()

    def advance(self, dt: float) -> None:
        """Advance every device by ``dt`` seconds, capturing a frame at the first grid instant
        (``grid_s``) at or after each frame time."""
        end = self.clock.now() + dt
        grid = self.grid_s
        while (now := self.clock.now()) < end - 1e-12:
            capture = self._next_capture
            if math.isfinite(capture):  # onto the grid, counted from the clock's origin
                capture = now + max(0.0, math.ceil((capture - now) / grid - 1e-9) * grid)
            step_to = min(end, capture)
            if step_to > now:
                self._step(step_to - now)
            if self.clock.now() >= capture - 1e-12:
                self.on_capture(self.clock.now())
                self._next_capture += 1.0 / self.timing.fps

    def _step(self, dt: float) -> None:
        self._step_arm(dt)
        self.track_model.step(dt)
        self.gripper_model.step(dt)
        self.clock.advance(dt)
        X_WT = self.track_model.X_WT()
        X_TC = X_WT.inverse() @ self.arm.camera_pose_W()
        # Position first: the rotation's angle costs more and matters only at the ring.
        captured = (
            translation_error(X_TC, self._grasp_X_TC) <= self._capture_m
            and rotation_error_geodesic(X_TC, self._grasp_X_TC) <= self._capture_rad
        )
        self.gripper_model.set_object(self._object_width if captured else None)
        if self._tool_reach_m is not None:
            self.arm.set_contact_wrench(self.contact_wrench_B(X_WT, X_TC))

    def contact_wrench_B(self, X_WT: Pose, X_TC: Pose) -> np.ndarray:
        """The wrench at the flange, in B, of the fingertips pressed into the face plane: a
        spring k·δ along +z_T at the tip, and its moment about the flange."""
        assert self._tool_reach_m is not None
        tip_T = X_TC.apply(np.array([0.0, 0.0, self._tool_reach_m]))
        depth = -float(tip_T[2])
        if depth <= 0.0:
            return np.zeros(6)
        X_BT = self.arm.X_WB.inverse() @ X_WT
        force_B = X_BT.R @ np.array([0.0, 0.0, self._contact_stiffness * depth])
        lever_B = X_BT.apply(tip_T) - self.arm.T_BE[:3, 3]
        return np.concatenate([force_B, np.cross(lever_B, force_B)])

    def _step_arm(self, dt: float) -> None:
        """The arm's share of a step (an emulated controller drives it instead: emulated_world)."""
        self.arm.step(dt)

    def truth(self) -> Mapping[str, Pose]:
        return {"X_WT": self.track_model.X_WT(), "X_WC": self.arm.camera_pose_W()}

    def close(self) -> None:
        for device in ("camera", "gripper", "track", "arm"):
            if hasattr(self, device):
                with contextlib.suppress(Exception):
                    getattr(self, device).close()
        for server in self._servers:
            server.stop()
        self._servers.clear()

    def __enter__(self) -> SimRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SimWorld(SimRig):
    """The simulated rig with its camera: a pybullet scene of the mock-up rendered at every
    capture instant, each frame reaching the host after the configured latency."""

    def __init__(
        self,
        rig: RigConfig,
        mockup: MockupConfig,
        camera: CameraConfig,
        *,
        noise: NoiseConfig,
        render: RenderConfig,
        seed: int,
        **rig_options,
    ):
        self.scene: MockupScene | None = None
        super().__init__(rig, **rig_options)
        try:
            self.scene = MockupScene(mockup, X_WT=self.track_model.X_WT())
            self.renderer = make_renderer(self.scene, camera.camera_info(), render)
            self.camera = StreamingSimCamera(
                SimCamera(self.renderer, self.viewpoint, noise, seed=seed, clock=self.clock.now),
                latency_s=self.timing.latency_s,
                jitter_s=self.timing.jitter_s,
                seed=seed,
                clock=self.clock.now,
            )
        except Exception:
            self.close()
            raise

    def devices(self) -> tuple:
        return (self.arm, self.track, self.gripper, self.camera)

    def on_capture(self, stamp: float) -> None:
        assert self.scene is not None
        self.scene.set_pose(self.track_model.X_WT())
        self.camera.capture()

    def close(self) -> None:
        super().close()
        if self.scene is not None:
            self.scene.close()
            self.scene = None

    def __enter__(self) -> SimWorld:
        return self
