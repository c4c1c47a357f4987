"""``PYTHONPATH=. python -m hil.analysis.bench_rig``: what the emulated rig costs beside the
simulated one, on the wall clock.

The same short approach (``short_trial``: a start 0.6 m from the ring face — or ``--distance`` —,
a 160×120 camera at 10 fps, the oracle estimator of tests/hil/fake_estimators.py: vision is not
the subject) runs twice: every device simulated, then the real drivers (ur-rtde, pymodbus)
against the emulated world. For each: the outcome, each process's CPU share over the loop's run
(the vision process's workers included), the control tick's work and period percentiles. Every
figure moves with the machine's load: compare within one run. The CI tests of the emulated rig
(tests/hil/runtime/test_emulated_trial.py) run the same short trial.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from configuration.rig import load_rig
from configuration.simulation import SimulationConfig
from hil.logs.triallog import TrialLog
from hil.runtime.compose import Trial
from hil.runtime.processes import child_pids, cpu_seconds
from sim_backends.ur_emulator import free_loopback_host

ORACLE = "tests.hil.fake_estimators:build_oracle"


#: The longest stall the short trial forgives (s): its devices' time-outs, the track's command
#: watchdog and its tick deadline. A rig's are 0.1 s, 0.1 s and 24 ms (configs/real.yaml;
#: configs/emulated.yaml too). Here the emulators share two cores with the control loop, the
#: vision processes and whatever else runs: with this trial alone on the shared 2-core machine,
#: everything stalled for up to 0.26 s now and then (no Modbus request served, the control tick
#: itself 0.12 s late), and about one trial in ten ended on "no reply within 0.1 s"; once in CI
#: the track stopped itself after "no command from the control loop for 0.104 s". A longer stall
#: is still a fault, and the injected faults still stop the arm.
SHARED_MACHINE_STALL_S = 0.3


def emulated_devices() -> dict:
    """Emulated arm, track and gripper, each on a loopback address nobody else uses now, with
    the shared machine's time-outs (``SHARED_MACHINE_STALL_S``)."""
    modbus = free_loopback_host()
    timeout = SHARED_MACHINE_STALL_S
    return {
        "arm": {
            "backend": "ur_rtde",
            "emulate": True,
            "host": free_loopback_host(),
            "state_timeout_s": timeout,
            "watchdog_min_frequency_hz": 1.0 / timeout,
        },
        "camera": {"backend": "sim"},
        "track": {
            "backend": "modbus", "emulate": True, "host": modbus, "port": 5020,
            "timeout_s": timeout, "command_timeout_s": timeout,
        },
        "gripper": {
            "backend": "modbus", "emulate": True, "host": modbus, "port": 5021,
            "timeout_s": timeout,
        },
    }  # fmt: skip


def short_trial(
    directory: Path,
    *,
    distance_m: float = 0.6,
    devices: dict | None = None,
    systems: tuple[str, ...] = (ORACLE,),
    **changes,
) -> SimulationConfig:
    """A short wall-clock trial, cheap enough for CI: the track starts ``2.5 − distance_m``
    along (the camera ``distance_m`` from the ring), a 160×120 camera at 10 fps, a short guarded
    move, and vision ages of 2 s that forgive a loaded machine's late frames (at load average 19
    the vision process, at normal priority beside the SCHED_FIFO world and control loop, went
    over a second without a result, and a 1 s coast ended the grasp). Emulated devices unless
    ``devices`` says otherwise ({}: simulated). Writes its camera and rig files to
    ``directory``."""
    camera = directory / "small_camera.yaml"
    camera.write_text("name: small\nwidth: 160\nheight: 120\nhfov_deg: 70\n")
    rig = load_rig("rig").model_dump(mode="json")
    rig["track"]["start_position"] = 2.5 - distance_m
    rig_path = directory / "rig_short.yaml"
    rig_path.write_text(yaml.safe_dump(rig))
    data = {
        "name": "short",
        "camera": str(camera),
        "rig": str(rig_path),
        "systems": list(systems),
        "noise": {"preset": "none"},
        "clock": "wall",
        "camera_timing": {"fps": 10, "latency_s": 0.12, "jitter_s": 0.01},
        "vision": {"log_frames_every_s": 0, "max_frame_age_s": 2.0},
        "fusion": {"coast_timeout_s": 2.0, "lost_timeout_s": 4.0},
        "start": {"distance_m": distance_m, "max_offset_m": 0.03, "max_rotation_deg": 2.0},
        "approach": {
            "standoff": {"dwell_s": 0.3},
            "grasp": {"advance_m": 0.04, "speed": 0.03, "hold_s": 0.2},
            # A short trial shows the plumbing on a shared machine: ages, the tick deadline and
            # the devices' time-outs are relaxed; docs/realtime.md measures the real ones.
            "supervisor": {
                "max_estimate_age_s": 2.0,
                "max_frame_age_s": 2.0,
                "max_tick_s": SHARED_MACHINE_STALL_S,
            },
        },
        "devices": emulated_devices() if devices is None else devices,
        "max_duration_s": 40.0,
    }
    data.update(changes)
    return SimulationConfig.model_validate(data)


def measure(sim: SimulationConfig, log_path: Path, seed: int = 1) -> str:
    """Run ``sim`` and describe it in a few lines (see the module docstring)."""
    marks: dict = {}

    def on_tick(record) -> None:
        if record.tick == 0:
            pids = {name: p.pid for name, p in trial.processes.items()}
            pids |= {f"worker{i}": pid for i, pid in enumerate(child_pids(pids["vision"]))}
            pids["control"] = os.getpid()
            marks.update(pids=pids, t0=time.monotonic())
            marks["cpu0"] = {name: cpu_seconds(pid) for name, pid in pids.items()}

    started = time.monotonic()
    with Trial(sim, seed=seed, log_path=log_path, on_tick=on_tick) as trial:
        built = time.monotonic()
        result = trial.run()
        elapsed = time.monotonic() - marks["t0"]
        cpu = {n: cpu_seconds(p) - marks["cpu0"][n] for n, p in marks["pids"].items()}
    torn_down = time.monotonic() - started - (built - started) - elapsed
    ticks = list(TrialLog.open(log_path).ticks())
    work = np.array([t.timing.work_ms for t in ticks])
    period = np.array([t.timing.period_ms for t in ticks[1:]])
    o = result.outcome
    shares = ", ".join(f"{n} {100 * c / elapsed:.0f}" for n, c in cpu.items())
    return "\n".join(
        [
            f"{sim.devices.kind}: {'success' if result.success else 'failure'} ({o.phase} "
            f"{o.abort_reason!r}) after {o.duration_s:.1f} s, {o.ticks} ticks, "
            f"{o.deadline_misses} deadline misses; start-up {built - started:.1f} s, "
            f"teardown {torn_down:.1f} s",
            f"  CPU, % of a core over the run: {shares}; total {100 * sum(cpu.values()) / elapsed:.0f}",
            "  tick work ms p50/p99/max "
            + " / ".join(f"{v:.1f}" for v in np.percentile(work, [50, 99, 100]))
            + ", period ms p50/p99/max "
            + " / ".join(f"{v:.1f}" for v in np.percentile(period, [50, 99, 100])),
        ]
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--distance", type=float, default=0.9, help="start distance (m)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        directory = Path(folder)
        for name, devices in (("simulated", {}), ("emulated", None)):
            sim = short_trial(directory, distance_m=args.distance, devices=devices, name=name)
            print(measure(sim, directory / f"{name}.mcap"), flush=True)


if __name__ == "__main__":
    main()
