"""Where things stand on the rig, and whether the arm can do its part of the approach.

Pure functions of the rig configuration (no device, no pybullet):

* ``carriage_pose_W`` / ``target_pose_W``: the carriage and the mock-up at a track position
  (no drift);
* ``camera_pose_W``: the camera at joint angles q (``X_WB·X_BE(q)·X_EC``);
* ``view_of_target``: how the camera sees the ring face — distance along the optical axis,
  off-axis offset, angle between the optical axis and the face normal;
* ``reach_check``: the camera moved through the box the approach needs from the start pose
  (sideways and up/down ±0.30 m, turned ±10° about each axis, backed off and advanced along the
  optical axis), solved by inverse kinematics continued from the start joints, with the margins
  that matter: IK failures, smallest Jacobian singular value σ_min (distance to singularity),
  Yoshikawa manipulability, elbow extension (shoulder–wrist distance over |a2|+|a3|; 1 = arm
  stretched straight, the reach boundary) and distance to the joint ranges.

``python -m sim_backends.rig_geometry [rig.yaml]`` prints these for a rig;
``--sweep MODEL`` scans flange placements for a model, to compare arms.
"""

from __future__ import annotations

import argparse
import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from configuration.rig import ArmConfig, RigConfig, TrackConfig, load_rig
from drivers.ur_kinematics import (
    forward_kinematics,
    jacobian_from_frames,
    joint_frames,
    manipulability,
    solve_ik,
    ur_model,
)
from estimators.geometry import Pose


def carriage_pose_W(track: TrackConfig, position: float) -> Pose:
    """``X_WM`` at track ``position`` (m)."""
    X_WM0 = track.X_WM0.pose
    return Pose(X_WM0.R, X_WM0.p + position * track.axis_unit_W)


def target_pose_W(track: TrackConfig, position: float) -> Pose:
    """``X_WT`` at track ``position``, mount drift excluded."""
    return carriage_pose_W(track, position) @ track.X_MT.pose


def camera_pose_W(arm: ArmConfig, q: np.ndarray | None = None) -> Pose:
    """``X_WC`` with the arm at ``q`` (rad; default its start joints ``q0_deg``)."""
    q = np.radians(arm.q0_deg) if q is None else np.asarray(q, dtype=float)
    return arm.X_WB.pose @ forward_kinematics(ur_model(arm.model), q) @ arm.X_EC.pose


@dataclass(frozen=True, slots=True)
class View:
    """The ring face seen from the camera: ``distance`` (m, along the optical axis),
    ``off_axis`` (m, ring centre from the optical axis), ``tilt_deg`` (optical axis vs the
    face's inward normal −z_T; 0 = square on)."""

    distance: float
    off_axis: float
    tilt_deg: float


def view_of_target(X_WC: Pose, X_WT: Pose) -> View:
    p_CT = X_WC.inverse().apply(X_WT.p)
    z_C = X_WC.R[:, 2]
    normal_in = -X_WT.R[:, 2]
    tilt = math.degrees(math.acos(float(np.clip(z_C @ normal_in, -1.0, 1.0))))
    return View(float(p_CT[2]), float(np.hypot(p_CT[0], p_CT[1])), tilt)


def track_position_at_distance(rig: RigConfig, distance: float) -> float:
    """Track position putting the ring face ``distance`` (m) in front of the start camera
    (along the optical axis; linear in the position because the track is straight)."""
    X_WC = camera_pose_W(rig.arm)
    d0 = view_of_target(X_WC, target_pose_W(rig.track, 0.0)).distance
    d1 = view_of_target(X_WC, target_pose_W(rig.track, 1.0)).distance
    if abs(d1 - d0) < 1e-9:
        raise ValueError("the track does not move the mock-up along the camera's optical axis")
    return (distance - d0) / (d1 - d0)


@dataclass(frozen=True, slots=True)
class ReachCheck:
    """Margins of the arm over the approach's camera box (see module docstring)."""

    poses: int
    failures: int
    sigma_min_start: float
    sigma_min: float
    manipulability_min: float
    extension_max: float
    joint_margin_min_deg: float


def camera_box(
    lateral: float = 0.30,
    rotation_deg: float = 10.0,
    forward: tuple[float, ...] = (-0.10, 0.0, 0.20),
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera displacements (in C: x, y sideways/up-down, z forward) and rotations (rotation
    vectors in C): a 3×3 grid of lateral offsets × the forward steps × no turn or the 8 corners
    of ±``rotation_deg`` about all three axes (the per-axis angle, as in the reference study)."""
    turns = [np.zeros(3)] + [
        math.radians(rotation_deg) * np.array(signs)
        for signs in itertools.product((-1.0, 1.0), repeat=3)
    ]
    grid = (-lateral, 0.0, lateral)
    return [
        (np.array([dx, dy, dz]), turn)
        for dx, dy in itertools.product(grid, grid)
        for dz in forward
        for turn in turns
    ]


def reach_check(
    arm: ArmConfig, box: list[tuple[np.ndarray, np.ndarray]] | None = None
) -> ReachCheck:
    """IK over the camera ``box`` (default ``camera_box()``) around the start pose."""
    model = ur_model(arm.model)
    q0 = np.radians(arm.q0_deg)
    X_BW = arm.X_WB.pose.inverse()
    X_CE = arm.X_EC.pose.inverse()
    X_WC0 = camera_pose_W(arm, q0)
    reach = abs(model.a[1]) + abs(model.a[2])
    sigmas, manip, extension, margins = [], [], [], []
    failures = 0
    box = camera_box() if box is None else box
    for offset_C, turn_C in box:
        X_C0C = Pose(Rotation.from_rotvec(turn_C).as_matrix(), offset_C)
        X_BE = X_BW @ X_WC0 @ X_C0C @ X_CE
        q, ok = solve_ik(model, X_BE, q0)
        if not ok:
            failures += 1
            continue
        frames = joint_frames(model, q)
        J = jacobian_from_frames(frames)
        sigmas.append(float(np.linalg.svd(J, compute_uv=False)[-1]))
        manip.append(manipulability(J))
        extension.append(float(np.linalg.norm(frames[3][:3, 3] - frames[1][:3, 3])) / reach)
        margins.append(float(np.min(np.minimum(q - model.lower, model.upper - q))))
    J0 = jacobian_from_frames(joint_frames(model, q0))
    nan = math.nan
    return ReachCheck(
        poses=len(box),
        failures=failures,
        sigma_min_start=float(np.linalg.svd(J0, compute_uv=False)[-1]),
        sigma_min=min(sigmas, default=nan),
        manipulability_min=min(manip, default=nan),
        extension_max=max(extension, default=nan),
        joint_margin_min_deg=math.degrees(min(margins, default=nan)),
    )


def _flange_forward_config(
    model_name: str, r: float, h: float, q_seed_deg: tuple
) -> ArmConfig | None:
    """An arm at the W origin whose flange is ``r`` ahead (+x) and ``h`` above the base,
    pointing along +x with the rig's camera mount; None if IK finds no such pose."""
    R_BE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    q, ok = solve_ik(
        ur_model(model_name), Pose(R_BE, np.array([r, 0.0, h])), np.radians(q_seed_deg)
    )
    if not ok:
        return None
    return ArmConfig(
        model=model_name,
        q0_deg=tuple(float(v) for v in np.degrees(q)),
        X_EC={"xyz": (0.0, -0.07, 0.05)},
        joint_limit_margin_deg=0.0,
    )


def _print_rig(rig: RigConfig) -> None:
    X_WC = camera_pose_W(rig.arm)
    print(f"rig {rig.name!r}: arm {rig.arm.model}, camera at {np.round(X_WC.p, 3)} m in W")
    for label, position in (
        ("track start", rig.track.start_position),
        ("stand-off 0.5 m", track_position_at_distance(rig, 0.5)),
        ("travel max", rig.track.travel_max),
    ):
        view = view_of_target(X_WC, target_pose_W(rig.track, position))
        print(
            f"  {label:16s} s = {position:6.3f} m: ring face {view.distance:.3f} m ahead, "
            f"{view.off_axis * 1000:.1f} mm off axis, tilt {view.tilt_deg:.2f}°"
        )
    check = reach_check(rig.arm)
    print(
        f"  camera box ±0.30 m, ±10°, −0.10…+0.20 m forward ({check.poses} poses): "
        f"{check.failures} IK failures; σ_min {check.sigma_min:.3f} (start {check.sigma_min_start:.3f}); "
        f"manipulability ≥ {check.manipulability_min:.4f}; elbow extension ≤ {check.extension_max:.2f}; "
        f"joint-range margin ≥ {check.joint_margin_min_deg:.0f}°"
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rig", nargs="?", default="rig", help="rig YAML (default: built-in rig)")
    parser.add_argument("--sweep", metavar="MODEL", help="scan flange placements for an arm model")
    args = parser.parse_args(argv)
    if args.sweep is None:
        _print_rig(load_rig(args.rig))
        return
    seeds = {"ur5e": (161, -77, 121, -45, 71, 180)}
    seed = seeds.get(args.sweep, (165, -44, 111, 113, -75, 0))
    reach = ur_model(args.sweep).reach
    print(f"{args.sweep}: flange r ahead of / h above the base, camera box as for the rig")
    for r in np.round(reach * np.array([0.35, 0.45, 0.55, 0.65, 0.75]), 3):
        for h in (0.0, 0.15, 0.30):
            arm = _flange_forward_config(args.sweep, float(r), h, seed)
            if arm is None:
                print(f"  r={r:.2f} h={h:.2f}: unreachable")
                continue
            c = reach_check(arm)
            print(
                f"  r={r:.2f} h={h:.2f}: failures {c.failures:3d}/{c.poses}, σ_min {c.sigma_min:.3f}, "
                f"extension ≤ {c.extension_max:.2f}"
            )


if __name__ == "__main__":
    main()
