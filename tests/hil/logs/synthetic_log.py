"""A synthetic but realistic approach trial, as the control loop and the vision pipeline would
log it (format 2: typed records), for tests of logs, reports and comparisons.

The camera closes from 2.5 m to a 0.5 m stand-off in front of the default mock-up (target at
the world origin, slightly displaced and turned), holds, grasps and retreats. Two rates:

- the control loop ticks at ``rate_hz``; each ``TickRecord`` carries wall-clock timing with a
  known jitter and a few injected deadline misses (a tick that started 1.5 periods late);
- the camera captures frames at ``camera_hz`` while the approach runs; a frame arrives
  ``LATENCY_S`` (± 10 ms) after its capture, every ``DROP_EVERY``-th one is dropped (superseded
  before an estimator was free), and each system processes the others for a known time and
  hands its result to fusion at ``t = arrival + processing``: one ``VisionRecord`` per result,
  with the truth at the capture instant. ``corners`` and ``lines`` give 6-DOF poses,
  ``ellipses`` the 5-DOF pose of ``ring_outer``, with known, distance-dependent errors. Some
  results are lost (``not_measured``), some ``lines`` outliers are rejected by the gate, and
  a few results come too late (``stale``).

The fused estimate at a tick errs by 0.3–0.7 × the smallest error of the valid results of the
frame captured nearest that tick (when there is none, it keeps the previous error × 1.2).

Every injected value is returned (``SyntheticTrial``), so analyses can be checked against what
was put in rather than against themselves. Deterministic for a seed.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from configuration.camera import load_camera
from configuration.mockup import load_mockup
from estimators.geometry import Pose
from estimators.measurement import Measurement
from hil.evaluation.scenarios import camera_pose_for, target_offset
from hil.logs.records import (
    ArmRecord,
    CommandRecord,
    EstimateRecord,
    GripperRecord,
    TickRecord,
    TimingRecord,
    TrackRecord,
    TruthRecord,
    VisionCounters,
    VisionRecord,
)
from hil.logs.triallog import TrialLogWriter

SYSTEMS = ("corners", "lines", "ellipses")
#: 1σ-ish error scales: position (m) = k_p·d², attitude (rad) = k_θ·d, d in m.
ERROR_SCALES = {
    "corners": (0.003, math.radians(0.5)),
    "lines": (0.005, math.radians(0.8)),
    "ellipses": (0.002, math.radians(0.3)),
}
#: Median processing time per system (s); each result takes 0.8–1.2 × this.
PROCESSING_S = {"corners": 0.030, "lines": 0.045, "ellipses": 0.060}
LATENCY_S = 0.120  # capture → arrival, ± 10 ms
#: Captures (mid-exposure) fall between control ticks, never half-way: the tick nearest a
#: capture is unambiguous.
EXPOSURE_OFFSET_S = 0.013
DROP_EVERY = 9  # frame k is dropped when k % DROP_EVERY == 4
STALE_EXTRA_S = 0.250  # a stale result's processing overran by this much
MAX_FRAME_AGE_S = 0.300
STANDOFF_M = 0.5
START_M = 2.5
#: True camera error at the stand-off reported by the outcome event of a completed trial.
STANDOFF_ERROR = (0.0012, math.radians(0.04))
#: Phase schedule: (phase, duration in s); approach lasts until the stand-off is reached.
SCHEDULE = (
    ("idle", 0.5),
    ("acquire", 1.0),
    ("approach", 16.0),
    ("standoff", 2.0),
    ("grasp", 1.0),
    ("retreat", 1.5),
    ("done", 0.0),
)
ACTIVE = ("acquire", "approach", "standoff", "grasp", "retreat")


#: The share of a synthetic tick's work spent on the CPU (``TimingRecord.cpu_ms``).
CPU_SHARE = 0.75


@dataclass
class SyntheticTrial:
    """Records and events as the loop would log them, and what was injected.

    ``errors[system]`` = (position error (m), attitude error (rad)) arrays over that system's
    vision records in capture order (NaN where the result was lost), ``errors["fused"]`` the
    same over ticks (NaN without an estimate); ``status[system]``: each of its results'
    outcome, in capture order. ``period_ms`` / ``work_ms`` / ``deadline_miss``: per tick
    (``period_ms`` NaN at the first; the tick's CPU time is ``CPU_SHARE`` of its work);
    ``latency_ms[system]`` / ``processing_ms[system]``: per result that reached fusion (not
    stale) / per result; ``frames``: the camera's frames (seq, capture, arrival, dropped);
    ``frame_counts``: (received, processed, dropped) at the end."""

    header: dict[str, Any]
    rate_hz: float
    ticks: list[TickRecord] = field(default_factory=list)
    vision: list[VisionRecord] = field(default_factory=list)
    events: list[tuple[float, str, str, dict]] = field(default_factory=list)
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    status: dict[str, list[str]] = field(default_factory=dict)
    period_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    work_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    deadline_miss: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    latency_ms: dict[str, np.ndarray] = field(default_factory=dict)
    processing_ms: dict[str, np.ndarray] = field(default_factory=dict)
    frames: list[tuple[int, float, float, bool]] = field(default_factory=list)
    frame_counts: tuple[int, int, int] = (0, 0, 0)
    #: Capture times of the frames ``write_trial`` wrote as images.
    image_t: list[float] = field(default_factory=list)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _perturb(X: Pose, position_m: float, angle_rad: float, rng: np.random.Generator) -> Pose:
    """``X`` moved by ``position_m`` and turned by ``angle_rad`` (left-multiplied, in C)."""
    R = Rotation.from_rotvec(_unit(rng) * angle_rad).as_matrix() @ X.R
    return Pose(R, X.p + _unit(rng) * position_m)


def _turn(normal: np.ndarray, angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    axis = np.cross(normal, _unit(rng))
    axis /= np.linalg.norm(axis)
    return Rotation.from_rotvec(axis * angle_rad).as_matrix() @ normal


def _phase_at(t: float) -> tuple[str, float]:
    start = 0.0
    for phase, duration in SCHEDULE:
        if t < start + duration or duration == 0.0:
            return phase, t - start
        start += duration
    return "done", 0.0


def distance_at(t: float) -> float:
    """Camera to ring face at trial time ``t``: a smooth (cosine) closing from START_M to
    STANDOFF_M during the approach, a slow retreat after the grasp."""
    phase, t_phase = _phase_at(t)
    if phase in ("idle", "acquire"):
        return START_M
    if phase == "approach":
        s = min(max(t_phase / SCHEDULE[2][1], 0.0), 1.0)
        return STANDOFF_M + (START_M - STANDOFF_M) * 0.5 * (1.0 + math.cos(math.pi * s))
    if phase == "retreat":
        return STANDOFF_M + 0.15 * t_phase
    if phase == "done":
        return STANDOFF_M + 0.15 * SCHEDULE[5][1]
    return STANDOFF_M


def _closing_speed(t: float) -> float:
    phase, t_phase = _phase_at(t)
    if phase != "approach":
        return 0.0
    duration = SCHEDULE[2][1]
    return (
        (START_M - STANDOFF_M) * math.pi / (2 * duration) * math.sin(math.pi * t_phase / duration)
    )


OFFSET = target_offset(0.03, -0.02, 0.0, math.radians(2.0), math.radians(-3.0), 0.04)


def _truth(t: float) -> tuple[Pose, Pose]:
    """(X_WC, X_CT) at trial time ``t``."""
    return camera_pose_for(distance_at(t), OFFSET)


def _measure(
    system: str,
    seq: int,
    capture_t: float,
    rng: np.random.Generator,
    ring,
    outlier: bool,
) -> tuple[Measurement, float, float]:
    """A valid measurement of frame ``seq`` and its injected (position, attitude) error."""
    distance = distance_at(capture_t)
    _, X_CT = _truth(capture_t)
    k_p, k_theta = ERROR_SCALES[system]
    e_p = k_p * distance**2 * float(np.linalg.norm(rng.normal(size=3)))
    e_theta = k_theta * distance * float(np.linalg.norm(rng.normal(size=3)))
    if outlier:
        e_p, e_theta = 10 * e_p + 0.05, 10 * e_theta + math.radians(5)
    status = "acquired" if seq == 0 else "tracking"
    if system == "ellipses":
        m = Measurement(
            system,
            status,
            capture_t,
            seq,
            circle="ring_outer",
            center_C=X_CT.apply(ring.center_T) + _unit(rng) * e_p,
            normal_C=_turn(X_CT.R @ ring.normal_T, e_theta, rng),
            covariance_5dof=np.diag(
                [(k_p * distance**2) ** 2] * 3 + [(k_theta * distance) ** 2] * 2
            ),
            residual_px=float(rng.uniform(0.1, 0.4)),
        )
    else:
        m = Measurement(
            system,
            status,
            capture_t,
            seq,
            X_CT=_perturb(X_CT, e_p, e_theta, rng),
            covariance=np.diag([(k_theta * distance) ** 2] * 3 + [(k_p * distance**2) ** 2] * 3),
            residual_px=float(rng.uniform(0.2, 0.6)) * (8 if outlier else 1),
        )
    return m, e_p, e_theta


def make_trial(
    *,
    seed: int = 0,
    rate_hz: float = 25.0,
    camera_hz: float = 10.0,
    with_truth: bool = True,
    abort_at_s: float | None = None,
    lost_probability: float = 0.03,
    outlier_probability: float = 0.04,
    stale_probability: float = 0.02,
    miss_every: int = 97,
) -> SyntheticTrial:
    """Generate the trial (see the module docstring). ``abort_at_s`` ends it with an abort
    (stop commanded, ``abort`` event) at that time instead of completing. Tick ``i`` with
    ``i % miss_every == 50`` starts 1.5 periods late: a deadline miss."""
    rng = np.random.default_rng(seed)
    mockup = load_mockup("default")
    ring = mockup.target_model().circle("ring_outer")
    period_s = 1.0 / rate_hz
    header = {
        "config": {
            "mockup": mockup.model_dump(mode="json"),
            "camera": load_camera("reference").model_dump(mode="json"),
            "approach": {"servo": {"control_rate_hz": rate_hz}, "standoff_m": STANDOFF_M},
            "backend": "sim" if with_truth else "real",
        },
        "seed": seed,
        "notes": "synthetic approach (tests/hil/logs/synthetic_log.py)",
    }
    trial = SyntheticTrial(header=header, rate_hz=rate_hz)
    end_s = sum(d for _, d in SCHEDULE)
    if abort_at_s is not None:
        end_s = min(end_s, abort_at_s + 0.5)

    # --- vision: frames while a phase that uses vision runs ---------------------------------
    frames: list[tuple[int, float, float, bool]] = []  # seq, capture, arrival, dropped
    capture_t, seq = SCHEDULE[0][1] + EXPOSURE_OFFSET_S, 0
    while capture_t < end_s:
        if _phase_at(capture_t)[0] in ACTIVE and (abort_at_s is None or capture_t < abort_at_s):
            arrival = capture_t + LATENCY_S + float(rng.uniform(-0.010, 0.010))
            frames.append((seq, capture_t, arrival, seq % DROP_EVERY == 4))
            seq += 1
        capture_t = round(capture_t + 1.0 / camera_hz, 9)
    injected: dict[tuple[str, int], tuple[float, float]] = {}  # (system, seq) → errors
    frame_errors: dict[int, list[float]] = {}  # seq → valid position errors
    frame_attitude: dict[int, list[float]] = {}
    for seq, capture, arrival, dropped in frames:
        if dropped:
            continue
        for i, system in enumerate(SYSTEMS):
            started = arrival + 0.001 * i
            duration = PROCESSING_S[system] * float(rng.uniform(0.8, 1.2))
            stale = rng.random() < stale_probability
            if stale:
                duration += STALE_EXTRA_S
            finished = started + duration
            outlier = system == "lines" and rng.random() < outlier_probability
            if rng.random() < lost_probability:
                m = Measurement(
                    system, "lost", capture, seq, reason="no candidate passed the checks"
                )
                e_p = e_theta = math.nan
            else:
                m, e_p, e_theta = _measure(system, seq, capture, rng, ring, outlier)
            m = dataclasses.replace(m, time_ms=1000.0 * duration)
            if stale:
                outcome = "stale"
                reason = f"frame {1000 * (finished - capture):.0f} ms old when the result came"
            elif not m.valid:
                outcome, reason = "not_measured", m.reason
            elif outlier:
                outcome, reason = "rejected", "Mahalanobis distance 31.2 > gate 16.8"
            else:
                outcome, reason = "accepted", ""
            trial.vision.append(
                VisionRecord(
                    t=finished,
                    system=system,
                    seq=seq,
                    capture_t=capture,
                    arrival_t=arrival,
                    started_t=started,
                    finished_t=finished,
                    outcome=outcome,
                    measurement=m,
                    reason=reason,
                    fused_at_t=None if stale else capture,
                    processing_ms=1000.0 * duration,
                    truth_X_CT=_truth(capture)[1] if with_truth else None,
                )
            )
            injected[system, seq] = (e_p, e_theta)
            if m.valid:
                frame_errors.setdefault(seq, []).append(e_p)
                frame_attitude.setdefault(seq, []).append(e_theta)
    trial.vision.sort(key=lambda r: r.t)
    trial.frames = frames

    # --- control ticks ----------------------------------------------------------------------
    n_ticks = math.floor(end_s * rate_hz + 1e-9) + 1
    fused_errors: list[tuple[float, float]] = []
    periods, works, misses = [], [], []
    previous_phase, fused_error = None, (0.02, 0.02)
    for tick in range(n_ticks):
        t = tick / rate_hz
        phase, t_phase = _phase_at(t)
        if abort_at_s is not None and t >= abort_at_s:
            phase = "abort"
        X_WC, X_CT = _truth(t)
        if phase != previous_phase:
            if previous_phase is not None:
                trial.events.append(
                    (
                        t,
                        "phase",
                        f"{previous_phase} → {phase}",
                        {"from": previous_phase, "to": phase},
                    )
                )
            if phase == "abort":
                trial.events.append(
                    (t, "abort", "estimate too old: 0.41 s > 0.30 s", {"age_s": 0.41})
                )
            previous_phase = phase

        # what the vision pipeline had handed over by now
        arrived = [f for f in frames if f[2] <= t]
        done = [r for r in trial.vision if r.t <= t]
        accepted = [r for r in done if r.outcome == "accepted"]
        estimate = EstimateRecord(health="uninitialized")
        fused_now = (math.nan, math.nan)
        if phase in ACTIVE and accepted:
            nearest = min(frames, key=lambda f: abs(f[1] - t))[0]
            if nearest in frame_errors:
                factor = float(rng.uniform(0.3, 0.7))
                fused_error = (
                    factor * min(frame_errors[nearest]),
                    factor * min(frame_attitude[nearest]),
                )
            else:  # the nearest frame gave nothing: the estimate coasts and its error grows
                fused_error = (fused_error[0] * 1.2, fused_error[1] * 1.2)
            X_CT_fused = _perturb(X_CT, fused_error[0], fused_error[1], rng)
            newest = max(r.capture_t for r in accepted)
            estimate = EstimateRecord(
                health="ok",
                X_CT=X_CT_fused,
                X_MT=X_CT_fused,  # the mock-up does not ride a track in this trial
                V_MT=np.zeros(6),
                covariance=np.diag([1e-6] * 6),
                age_s=t - newest,
                updated_t=newest,
            )
            fused_now = fused_error
        fused_errors.append(fused_now)

        late_ms = 1.5 * 1000.0 * period_s if tick % miss_every == 50 else 0.0
        period_ms = (
            math.nan if tick == 0 else 1000.0 * period_s * float(rng.uniform(0.98, 1.02)) + late_ms
        )
        work_ms = float(rng.uniform(0.5, 2.0))
        miss = late_ms > 0.0
        periods.append(period_ms)
        works.append(work_ms)
        misses.append(miss)

        stop = phase in ("abort", "done", "idle")
        closing = _closing_speed(t)
        V_BE = np.zeros(6) if stop else np.array([0.002, -0.001, 0.2 * closing, 0.0, 0.0, 0.003])
        gripped = phase in ("grasp", "retreat", "done")
        trial.ticks.append(
            TickRecord(
                t=t,
                tick=tick,
                phase=phase,
                range_m=None if estimate.X_CT is None else float(estimate.X_CT.p[2]),
                estimate=estimate,
                command=CommandRecord(
                    V_BE=V_BE,
                    stop=stop,
                    reason="estimate too old" if phase == "abort" else "",
                    track_velocity=0.0 if stop else 0.8 * closing,
                    gripper="grip" if phase == "grasp" and t_phase == 0.0 else None,
                ),
                timing=TimingRecord(
                    period_ms=None if tick == 0 else period_ms,
                    late_ms=late_ms,
                    work_ms=work_ms,
                    deadline_miss=miss,
                    cpu_ms=CPU_SHARE * work_ms,
                ),
                vision=VisionCounters(
                    frames_received=len(arrived),
                    frames_processed=sum(not f[3] for f in arrived),
                    frames_dropped=sum(f[3] for f in arrived),
                    results_stale=sum(r.outcome == "stale" for r in done),
                    newest_frame_t=arrived[-1][1] if arrived else None,
                ),
                arm=ArmRecord(
                    q=np.array([0.0, -1.2, 1.4, -0.2, 1.57, 0.0]) + 0.01 * t,
                    X_BE=Pose(np.eye(3), np.array([0.4, 0.0, 0.5 + 0.002 * t])),
                    V_BE=V_BE,
                ),
                track=TrackRecord(
                    position=START_M - distance_at(t), velocity=0.0 if stop else 0.8 * closing
                ),
                gripper=GripperRecord(position=1.0 if gripped else 0.0, object_detected=gripped),
                truth=TruthRecord(X_CT=X_CT, X_WT=Pose.identity(), X_WC=X_WC)
                if with_truth
                else None,
            )
        )
    last = trial.ticks[-1]
    trial.vision = [r for r in trial.vision if r.t <= last.t]
    counters = last.vision
    trial.frame_counts = (
        counters.frames_received,
        counters.frames_processed,
        counters.frames_dropped,
    )
    success = abort_at_s is None
    trial.events.append(
        (
            last.t,
            "outcome",
            "success" if success else "failure",
            {
                "phase": last.phase,
                "abort_reason": None if success else "estimate too old: 0.41 s > 0.30 s",
                "success": success,
                "standoff_error_m": STANDOFF_ERROR[0] if success and with_truth else None,
                "standoff_error_rad": STANDOFF_ERROR[1] if success and with_truth else None,
                "deadline_misses": int(sum(misses)),
                "clock": "sim" if with_truth else "wall",
                "control_period_s": period_s,
            },
        )
    )
    for system in SYSTEMS:  # what was injected into the results the log holds
        results = sorted((r for r in trial.vision if r.system == system), key=lambda r: r.seq)
        trial.status[system] = [r.outcome for r in results]
        trial.errors[system] = tuple(
            np.array([injected[system, r.seq][k] for r in results]) for k in (0, 1)
        )
        trial.processing_ms[system] = np.array([r.processing_ms for r in results])
        trial.latency_ms[system] = np.array(
            [1000.0 * (r.finished_t - r.capture_t) for r in results if r.outcome != "stale"]
        )
    trial.errors["fused"] = (
        np.array([e[0] for e in fused_errors]),
        np.array([e[1] for e in fused_errors]),
    )
    trial.period_ms, trial.work_ms = np.array(periods), np.array(works)
    trial.deadline_miss = np.array(misses, dtype=bool)
    return trial


def synthetic_frame(range_m: float | None, *, width: int = 160, height: int = 120) -> np.ndarray:
    """A small grey image with the ring drawn at the size it has at ``range_m``."""
    image = np.full((height, width), 40, np.uint8)
    if range_m:
        radius = int(min(0.6 * width, 0.3 * 0.5 * width / max(range_m, 0.1)))
        cv2.circle(image, (width // 2, height // 2), radius, 200, 3)
    return image


def write_trial(
    path: str | Path,
    trial: SyntheticTrial,
    *,
    frames_every: int = 0,
    flush_interval_s: float = 1.0,
    trial_clock: bool = False,
    close: bool = True,
) -> TrialLogWriter:
    """Write ``trial`` to an MCAP trial log in the loop's order: at each tick the vision
    results handed to fusion since the last one, the images of ``frames_every``-th frames
    (0: none) at their capture time, the events, then the tick. ``trial_clock`` makes the
    writer flush on the trial's own time (as a simulation running faster than real time
    would) instead of the wall clock."""
    now = [0.0]
    clock = (lambda: now[0]) if trial_clock else time.monotonic
    writer = TrialLogWriter(path, trial.header, flush_interval_s=flush_interval_s, clock=clock)
    events = sorted(trial.events, key=lambda e: e[0])
    vision = list(trial.vision)
    images = [f for f in trial.frames if frames_every and f[0] % frames_every == 0]
    trial.image_t = []
    for record in trial.ticks:
        now[0] = record.t
        while vision and vision[0].t <= record.t:
            writer.write_vision(vision.pop(0))
        while images and images[0][2] <= record.t:  # kept when it arrived, stamped at capture
            _, capture, _, _ = images.pop(0)
            writer.write_frame(capture, synthetic_frame(distance_at(capture)))
            trial.image_t.append(capture)
        while events and events[0][0] <= record.t:
            t, kind, message, data = events.pop(0)
            writer.write_event(t, kind, message, **data)
        writer.write_tick(record)
    for t, kind, message, data in events:
        writer.write_event(t, kind, message, **data)
    if close:
        writer.close()
    return writer


def write_format1_log(path: str | Path) -> Path:
    """A small log as satgrasp wrote it before the typed records (format 1: the header, then
    tick dicts that held the measurements), with the MCAP writer directly."""
    import datetime as dt
    import json

    from mcap.writer import Writer

    from hil.logs.triallog import HEADER_METADATA, build_header

    header = build_header({"config": {}, "seed": 3}, dt.datetime(2026, 11, 20, tzinfo=dt.UTC))
    header["format_version"] = 1
    tick = {"t": 0.0, "tick": 0, "phase": "idle", "range_m": None, "measurements": []}
    path = Path(path)
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(library="satgrasp 0.9.0")
        writer.add_metadata(HEADER_METADATA, {k: json.dumps(v) for k, v in header.items()})
        schema = writer.register_schema("satgrasp.TrialHeader", "jsonschema", b"{}")
        for sequence, (topic, message) in enumerate(
            (("/trial/header", header), ("/trial/tick", tick))
        ):
            channel = writer.register_channel(topic, "json", schema)
            writer.add_message(channel, 0, json.dumps(message).encode(), 0, sequence)
        writer.finish()
    return path


def chunk_spans(path: str | Path) -> list[tuple[int, int]]:
    """(byte offset, byte length) of each chunk record of a complete MCAP file, from its index."""
    from mcap.reader import make_reader

    with Path(path).open("rb") as f:
        summary = make_reader(f).get_summary()
    return [(c.chunk_start_offset, c.chunk_length) for c in summary.chunk_indexes]


def flip_a_byte(path: str | Path, out: str | Path, offset: int) -> Path:
    """A copy of ``path`` with one bit of the byte at ``offset`` flipped (a bad sector)."""
    data = bytearray(Path(path).read_bytes())
    data[offset] ^= 0x10
    Path(out).write_bytes(bytes(data))
    return Path(out)
