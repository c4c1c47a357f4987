"""A simulated UR e-Series arm implementing ``drivers.base.Arm`` (speedL semantics).

Kinematic simulation at the controller's rate (500 Hz for e-Series): the model advances only in
``step(dt)`` — never by the wall clock — so a world loop can run it faster than real time. Each
control period:

1. the reference twist V_ref ramps toward the commanded twist at the configured TCP
   acceleration (like speedL's ``acc``; both parts scaled together so the ramp keeps its
   direction), or falls linearly to rest during a stop;
2. resolved-rate control: q̇ = J⁺ V_ref by damped least squares, damped only near a singularity
   (``ur_kinematics.damped_least_squares``; Nakamura & Hanafusa 1986, Chiaverini 1997), with J
   taken at the period's midpoint so the executed twist matches V_ref to second order;
3. limits, each applied by scaling the *whole* joint-velocity vector so the flange keeps its
   Cartesian direction: joint speed limits, a braking envelope that stops every joint at its
   range less the margin (|q̇_i| ≤ √(2·a·room)), then the joint acceleration limit (the largest
   q̇ on the ray of the desired one that every joint reaches within a·h);
4. q integrates with the trapezoid rule; X_BE and J come from the DH model (the same
   parameters as the shipped URDF).

Safety behaviour, modelled on a UR controller driven over RTDE: streaming servo commands arm a
watchdog — no ``servo`` within ``watchdog_s`` decelerates to rest and latches fault "watchdog";
streaming needs ``activate()`` after ``connect()`` (the control interface; ``stop`` works in
either state); a protective stop (``inject_protective_stop``), an emergency stop or an injected fault halts
the joints at the next control period and refuses motion (``DeviceFault``) until unlocked or
reset; a dropped link (``drop_link``) makes every call raise ``DeviceTimeout`` while the arm
keeps executing its last command (until its watchdog stops it).

The wrench at the TCP (``ArmState.wrench_B``, UR's ``getActualTCPForce``) is what the world
says touches the tool (``set_contact_wrench``; zero in free space): the arm stays kinematic,
as if the mock-up's mount yielded.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from configuration.rig import ArmConfig
from drivers.base import ArmState, DeviceError, DeviceFault, DeviceTimeout, ServoCommand
from drivers.ur_kinematics import (
    damped_least_squares,
    jacobian_from_frames,
    joint_frames,
    ur_model,
)
from estimators.geometry import Pose


class SimArm:
    """Simulated UR arm (``drivers.base.Arm``). ``clock`` stamps states (default: model time)."""

    def __init__(self, config: ArmConfig, *, clock: Callable[[], float] | None = None):
        self.config = config
        self.model = ur_model(config.model)
        self._period = 1.0 / config.control_rate_hz
        self._clock = clock
        self._X_WB = config.X_WB.pose
        self._X_EC = config.X_EC.pose
        published = np.array(self.model.max_joint_speed)
        if config.joint_speed_limit_deg_s is None:
            self._qd_max = published
        else:
            self._qd_max = np.radians(config.joint_speed_limit_deg_s)
            too_fast = np.flatnonzero(self._qd_max > published + 1e-9)
            if too_fast.size:
                i = int(too_fast[0])
                raise ValueError(
                    f"arm.joint_speed_limit_deg_s[{i}] exceeds the {self.model.name}'s maximum "
                    f"of {math.degrees(published[i]):.0f} deg/s"
                )
        self._qdd_max = math.radians(config.joint_acceleration_limit_deg_s2)
        margin = math.radians(config.joint_limit_margin_deg)
        self._q_low = self.model.lower + margin
        self._q_high = self.model.upper - margin
        self._q = np.radians(config.q0_deg)
        self._qd = np.zeros(6)
        self._time = 0.0
        self._pending = 0.0
        self._connected = False
        self._active = False
        self._link_dropped = False
        self._protective_stop = False
        self._emergency_stop = False
        self._fault: str | None = None
        self._fault_holds = False  # an injected fault holds the joints; the watchdog's does not
        self._mode = "idle"  # "speed": tracking a twist; "stopping": ramping to rest
        self._V_cmd = np.zeros(6)
        self._acceleration: float | None = None  # the command's own ramp (speedL acc), if any
        self._V_ref = np.zeros(6)
        self._stop_from = np.zeros(6)
        self._stop_duration = 0.0
        self._stop_elapsed = 0.0
        self._last_servo = 0.0
        self._limited_by: tuple[str, ...] = ()
        self._sigma_min = math.nan
        self._wrench_B = np.zeros(6)
        self._update_kinematics()

    # --- Arm protocol ---------------------------------------------------------------------
    def connect(self) -> None:
        if self._link_dropped:
            raise DeviceTimeout("SimArm.connect: the controller does not answer (link dropped)")
        self._connected = True

    def activate(self) -> None:
        """Take control (ur-rtde's control interface): ``servo`` is accepted from now on."""
        self._check_link("activate")
        self._refuse_if_halted("activate")
        self._active = True

    def deactivate(self) -> None:
        """Stop and give up control; the state stays readable."""
        if self._connected and not self._halted and self._mode != "idle":
            self._begin_stop(self.config.stop_deceleration)
        self._active = False

    def close(self) -> None:
        self.deactivate()  # a closed session stops the arm
        self._connected = False

    def state(self) -> ArmState:
        self._check_link("state")
        return ArmState(
            stamp=self._stamp(),
            q=self._q,
            X_BE=self._X_BE,
            V_BE=self._J @ self._qd,
            protective_stop=self._protective_stop,
            emergency_stop=self._emergency_stop,
            fault=self._fault,
            wrench_B=self._wrench_B,
        )

    def servo(self, command: ServoCommand) -> None:
        """Stream a flange twist ``V_BE`` (kept until changed or stopped) or a stop."""
        self._check_link("servo")
        if not isinstance(command, ServoCommand):
            raise TypeError(f"SimArm.servo expects a ServoCommand; got {type(command).__name__}")
        self._refuse_if_halted("servo")
        if not self._active:
            raise DeviceError("SimArm.servo refused: the arm is not active (call activate())")
        if command.stop:
            self._begin_stop(self.config.stop_deceleration)
            return
        V = np.array(command.V_BE, dtype=float)
        speed = float(np.linalg.norm(V[:3]))
        if speed > self.config.tcp_speed_limit:
            V *= self.config.tcp_speed_limit / speed  # direction kept
        self._V_cmd = V
        self._acceleration = command.acceleration
        self._mode = "speed"
        self._last_servo = self.time

    def stop(self, deceleration: float = 2.0) -> None:
        """Decelerate to rest: the twist falls linearly, linear part at ``deceleration`` m/s²
        and angular part at the same number in rad/s², both reaching zero together."""
        self._check_link("stop")
        if not (math.isfinite(deceleration) and deceleration > 0):
            raise ValueError(f"SimArm.stop: deceleration must be positive; got {deceleration}")
        if not self._halted:
            self._begin_stop(deceleration)

    # --- world-loop API -------------------------------------------------------------------
    @property
    def time(self) -> float:
        """Model time (s): the sum of the ``dt`` it was stepped by."""
        return self._time + self._pending

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def qd(self) -> np.ndarray:
        """Joint velocities (rad/s) at the last control period."""
        return self._qd.copy()

    @property
    def T_BE(self) -> np.ndarray:
        """``X_BE`` as a 4×4 matrix (a copy): for loops that cannot afford building a Pose."""
        return self._T_BE.copy()

    @property
    def V_BE(self) -> np.ndarray:
        """Flange twist ``J q̇`` = [v, ω] in B at the last control period."""
        return self._J @ self._qd

    @property
    def X_WB(self) -> Pose:
        return self._X_WB

    @property
    def X_EC(self) -> Pose:
        return self._X_EC

    @property
    def limited_by(self) -> tuple[str, ...]:
        """Which limits scaled the last control period's motion (empty when none did)."""
        return self._limited_by

    @property
    def sigma_min(self) -> float:
        """Smallest singular value of J at the last control period (distance to singularity)."""
        return self._sigma_min

    def step(self, dt: float) -> None:
        """Advance the controller by ``dt`` seconds, in periods of 1/control_rate_hz."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"SimArm.step: dt must be finite and ≥ 0; got {dt}")
        self._pending += dt
        while self._pending >= self._period - 1e-12:
            self._pending -= self._period
            self._control_period(self._period)

    def X_WE(self) -> Pose:
        return self._X_WB @ self._X_BE

    def camera_pose_W(self) -> Pose:
        """``X_WC = X_WB · X_BE · X_EC``."""
        return self._X_WB @ self._X_BE @ self._X_EC

    def camera_twist_C(self) -> np.ndarray:
        """Twist [v, ω] of the camera frame relative to W, expressed in C."""
        V_BE = self._J @ self._qd
        R_BC = self._X_BE.R @ self._X_EC.R
        p_EC_B = self._X_BE.R @ self._X_EC.p
        v_C_B = V_BE[:3] + np.cross(V_BE[3:], p_EC_B)
        return np.concatenate([R_BC.T @ v_C_B, R_BC.T @ V_BE[3:]])

    def set_joint_positions(self, q: np.ndarray) -> None:
        """Place the arm at rest at ``q`` (rad) — set-up only, not a motion."""
        q = np.asarray(q, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError(f"joint positions must be 6 finite values; got {q}")
        if np.any(q < self.model.lower) or np.any(q > self.model.upper):
            raise ValueError(
                f"joint positions {np.degrees(q).round(1)} deg outside the joint ranges"
            )
        self._q = q.copy()
        self._qd = np.zeros(6)
        self._V_ref = np.zeros(6)
        self._mode = "idle"
        self._update_kinematics()

    def set_contact_wrench(self, wrench_B: np.ndarray) -> None:
        """The wrench [f (N), τ (N·m)] in B that contact exerts at the TCP (the flange)."""
        wrench = np.array(wrench_B, dtype=float)
        if wrench.shape != (6,) or not np.all(np.isfinite(wrench)):
            raise ValueError(f"a wrench is 6 finite values [f (N), τ (N·m)]; got {wrench_B}")
        self._wrench_B = wrench

    # --- fault injection ------------------------------------------------------------------
    def inject_protective_stop(self) -> None:
        """The controller enters a protective stop: joints stop at the next control period."""
        self._protective_stop = True
        self._halt()

    def unlock_protective_stop(self) -> None:
        self._protective_stop = False

    def inject_emergency_stop(self) -> None:
        self._emergency_stop = True
        self._halt()

    def release_emergency_stop(self) -> None:
        self._emergency_stop = False

    def inject_fault(self, reason: str) -> None:
        """A controller fault named ``reason``: the joints stop at the next control period."""
        if not reason:
            raise ValueError("inject_fault needs a reason")
        self._fault = reason
        self._fault_holds = True
        self._halt()

    def reset_fault(self) -> None:
        """Clear a latched fault (an injected one, or "watchdog")."""
        self._fault = None
        self._fault_holds = False

    def drop_link(self) -> None:
        """The connection to the controller is lost: calls raise ``DeviceTimeout``."""
        self._link_dropped = True

    def restore_link(self) -> None:
        self._link_dropped = False

    # --- internals ------------------------------------------------------------------------
    def _refuse_if_halted(self, call: str) -> None:
        if self._emergency_stop:
            raise DeviceFault(f"SimArm.{call} refused: emergency stop")
        if self._protective_stop:
            raise DeviceFault(
                f"SimArm.{call} refused: protective stop (unlock_protective_stop() first)"
            )
        if self._fault is not None:
            raise DeviceFault(f"SimArm.{call} refused: arm fault {self._fault!r} (reset_fault())")

    def _check_link(self, call: str) -> None:
        if self._link_dropped:
            raise DeviceTimeout(f"SimArm.{call}: no answer from the controller (link dropped)")
        if not self._connected:
            raise DeviceError(f"SimArm.{call}: not connected (call connect())")

    def _stamp(self) -> float:
        return self._clock() if self._clock is not None else self._time

    @property
    def _halted(self) -> bool:
        """Joints held at rest: protective stop, emergency stop or an injected fault."""
        return self._protective_stop or self._emergency_stop or self._fault_holds

    def _halt(self) -> None:
        # No resumption of the old command after the cause is cleared.
        self._mode = "idle"
        self._V_cmd = np.zeros(6)

    def _begin_stop(self, deceleration: float) -> None:
        V_now = self._J @ self._qd
        self._stop_from = V_now
        self._stop_duration = (
            max(float(np.linalg.norm(V_now[:3])), float(np.linalg.norm(V_now[3:]))) / deceleration
        )
        self._stop_elapsed = 0.0
        self._V_cmd = np.zeros(6)
        self._mode = "stopping" if self._stop_duration > 0 else "idle"

    def _update_kinematics(self) -> None:
        frames = joint_frames(self.model, self._q)
        self._T_BE = frames[6]
        self._X_BE_cache: Pose | None = None  # built on demand: most periods nobody asks
        self._J = jacobian_from_frames(frames)

    @property
    def _X_BE(self) -> Pose:
        if self._X_BE_cache is None:
            self._X_BE_cache = Pose.unchecked(self._T_BE[:3, :3], self._T_BE[:3, 3])
        return self._X_BE_cache

    def _reference_twist(self, h: float) -> np.ndarray:
        cfg = self.config
        if self._mode == "speed":
            delta = self._V_cmd - self._V_ref
            if self._acceleration is not None:  # speedL's acc: m/s² and the same number in rad/s²
                linear_acc = angular_acc = self._acceleration
            else:
                linear_acc = cfg.tcp_acceleration
                angular_acc = math.radians(cfg.tcp_angular_acceleration_deg_s2)
            ratio = max(
                float(np.linalg.norm(delta[:3])) / (linear_acc * h),
                float(np.linalg.norm(delta[3:])) / (angular_acc * h),
                1.0,
            )
            return self._V_ref + delta / ratio
        if self._mode == "stopping":
            self._stop_elapsed += h
            remaining = max(0.0, 1.0 - self._stop_elapsed / self._stop_duration)
            if remaining == 0.0:
                self._mode = "idle"
            return self._stop_from * remaining
        return np.zeros(6)

    def _control_period(self, h: float) -> None:
        self._time += h
        if self._halted:
            self._qd = np.zeros(6)
            self._V_ref = np.zeros(6)
            self._limited_by = ()
            return
        if self._mode == "speed" and self._time - self._last_servo > self.config.watchdog_s:
            self._fault = "watchdog"
            self._begin_stop(self.config.stop_deceleration)
        self._V_ref = self._reference_twist(h)
        qd_des, self._sigma_min = self._resolve(self._J, self._V_ref)
        # Midpoint rule: solve again with J half a period ahead, so the twist executed over
        # the period matches V_ref to second order (with J(q) alone the direction drifts by
        # ~ω·h per period on a fast or stretched arm).
        q_mid = self._q + 0.25 * (self._qd + qd_des) * h
        qd_des, self._sigma_min = self._resolve(
            jacobian_from_frames(joint_frames(self.model, q_mid)), self._V_ref
        )
        limited = []
        if self._sigma_min < self.config.singularity_sigma:
            limited.append("singularity damping")
        ratio = float(np.max(np.abs(qd_des) / self._qd_max))
        if ratio > 1.0:
            qd_des /= ratio
            limited.append("joint speed")
        scale, joint = self._range_scale(qd_des, h)
        if scale < 1.0:
            qd_des *= scale
            limited.append(f"joint {joint + 1} range")
        qd_new = self._accelerate(qd_des, h, limited)
        self._q = self._q + 0.5 * (self._qd + qd_new) * h
        self._qd = qd_new
        self._limited_by = tuple(limited)
        self._update_kinematics()

    def _accelerate(self, qd_des: np.ndarray, h: float, limited: list[str]) -> np.ndarray:
        """Next joint velocity within the acceleration limit, on the ray of ``qd_des``.

        The largest s ∈ [0, 1] with |s·q̇_des,i − q̇_i| ≤ a·h for every joint keeps the flange's
        direction (only the speed along it drops); when no point of the ray is reachable in one
        period (the joint-space direction turned faster than the limit allows), the change
        toward ``qd_des`` is scaled instead and the path deviates a little.
        """
        step = self._qdd_max * h
        delta = qd_des - self._qd
        if np.max(np.abs(delta)) <= step:
            return qd_des
        if not np.any(qd_des):  # braking to rest: shrink q̇ along its own ray
            limited.append("joint acceleration")
            return self._qd * (1.0 - step / np.max(np.abs(self._qd)))
        lower, upper = 0.0, 1.0
        for d, c in zip(qd_des, self._qd, strict=True):
            if abs(d) < 1e-15:
                if abs(c) > step:
                    lower, upper = 1.0, 0.0  # this joint cannot stop in one period
                continue
            lo, hi = sorted(((c - step) / d, (c + step) / d))
            lower, upper = max(lower, lo), min(upper, hi)
        if lower <= upper:
            limited.append("joint acceleration")
            return upper * qd_des
        limited.append("joint acceleration (path deviation)")
        return self._qd + delta * (step / np.max(np.abs(delta)))

    def _resolve(self, J: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, float]:
        return damped_least_squares(
            J,
            V,
            sigma_threshold=self.config.singularity_sigma,
            damping_max=self.config.damping_max,
        )

    def _range_scale(self, qd: np.ndarray, h: float) -> tuple[float, int]:
        """Largest scale ≤ 1 of ``qd`` that lets every joint still brake (at the acceleration
        limit) before its range less the margin, and the joint that sets it."""
        a = self._qdd_max
        room = np.where(qd > 0, self._q_high - self._q, self._q - self._q_low)
        # room left after this period's travel (trapezoid: half of the current speed) must
        # hold the travel of this period's other half plus the braking distance:
        # v²/(2a) + v·h/2 ≤ room − |q̇|·h/2, solved for the largest v.
        room = np.maximum(room - 0.5 * np.abs(self._qd) * h, 0.0)
        allowed = a * (np.sqrt(0.25 * h * h + 2.0 * room / a) - 0.5 * h)
        speed = np.abs(qd)
        with np.errstate(divide="ignore", invalid="ignore"):
            scales = np.where(speed > allowed, allowed / speed, 1.0)
        joint = int(np.argmin(scales))
        return float(scales[joint]), joint
