"""Figures of the UR emulator driven by the real ur-rtde client and ``URArm``
(docs/ur_emulator.md): ``python -m sim_backends.ur_emulator.bench [--runs 5]``.

* servoL: a 250 Hz stream along a 5 cm line (1 s, then 0.3 s holding the goal; lookahead
  0.1 s, gain 300): final distance to the goal, largest distance from the line, largest lag;
* protective stop: from the first data package that carries it to ``URArm.state()`` showing
  it — polled as fast as possible (what the driver adds) and by a 125 Hz loop (state() then
  servo() every 8 ms, the control loop's pattern);
* speedL followed at once by kickWatchdog: the fraction of speedL commands the control script
  never read;
* URArm's lifecycle durations and the emulator's CPU use (idle, and moving at 125 Hz).

Every figure depends on the machine's load: compare within one run.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time

import numpy as np
import rtde_control
import rtde_receive

from drivers.base import DeviceFault, ServoCommand
from drivers.ur_rtde import URArm, URArmOptions
from sim_backends.ur_emulator.process import UREmulator, free_loopback_host

PERIOD = 0.008


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def servol_line(host: str) -> tuple[float, float, float]:
    """(final error, largest cross-track distance, largest lag behind the target), metres."""
    period = 1.0 / 250.0
    receive = rtde_receive.RTDEReceiveInterface(host, -1.0, ["actual_TCP_pose"])
    control = rtde_control.RTDEControlInterface(host)
    try:
        start = np.array(receive.getActualTCPPose())
        direction = np.array([0.6, -0.48, 0.64]) / np.linalg.norm([0.6, -0.48, 0.64])
        goal = start.copy()
        goal[:3] += 0.05 * direction
        cross, lag = [], []
        t0 = time.monotonic()
        for k in range(1, 326):
            target = start + min(k / 250, 1.0) * (goal - start)
            control.servoL(target.tolist(), 0.25, 0.5, period, 0.1, 300)
            offset = np.array(receive.getActualTCPPose()[:3]) - start[:3]
            along = offset @ direction
            cross.append(np.linalg.norm(offset - along * direction))
            lag.append(0.05 * min(k / 250, 1.0) - along)
            time.sleep(max(t0 + k * period - time.monotonic(), 0.0))
        control.servoStop(2.0)
        final = np.linalg.norm(np.array(receive.getActualTCPPose()[:3]) - goal[:3])
        control.stopScript()
    finally:
        control.disconnect()
        receive.disconnect()
    return float(final), float(max(cross)), float(max(lag))


def protective_stop_latency(
    emulator: UREmulator, arm: URArm, *, loop: bool, rng: np.random.Generator
) -> float:
    """Seconds from the first data package with the stop to ``state()`` showing it. The loop
    starts at a random phase of its period after the stop is raised, as a free-running control
    loop would meet it."""
    V = np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(10):
        arm.state()
        arm.servo(ServoCommand(time.monotonic(), V))
        time.sleep(PERIOD)
    emulator.protective_stop(program_keeps_running=True)
    t0 = time.monotonic() + (rng.uniform(0.0, PERIOD) if loop else 0.0)
    time.sleep(max(t0 - time.monotonic(), 0.0))
    k = 0
    while not (state := arm.state()).protective_stop:
        if loop:  # the control loop's pattern: state, command, sleep to the next period
            with contextlib.suppress(DeviceFault):  # it came between state() and servo()
                arm.servo(ServoCommand(time.monotonic(), V))
            k += 1
            time.sleep(max(t0 + k * PERIOD - time.monotonic(), 0.0))
        else:
            time.sleep(0.0002)
    latency = state.stamp - emulator.status().published["protective stop"]
    while arm.state().protective_stop:
        arm.unlock_protective_stop()
        time.sleep(0.01)
    return latency


def kick_race(host: str, commands: int = 200) -> int:
    """Send ``commands`` speedL commands each followed at once by kickWatchdog (the emulator's
    log then says which the script never read); returns how many were sent."""
    control = rtde_control.RTDEControlInterface(host)
    try:
        for _ in range(commands):
            control.speedL([0.005, 0.0, 0.0, 0.0, 0.0, 0.0], 1.0, 0.0)
            control.kickWatchdog()
            time.sleep(PERIOD)
        control.speedStop(2.0)
        control.stopScript()
    finally:
        control.disconnect()
    return commands


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=5, help="repetitions of each measurement")
    args = parser.parse_args()
    t = time.monotonic()
    with UREmulator(free_loopback_host(), unlock_delay_s=0.0) as emulator:
        print(f"emulator start (first, fork server included): {time.monotonic() - t:.2f} s")
        lines = [servol_line(emulator.host) for _ in range(args.runs)]
        final, cross, lag = (np.array(v) * 1e3 for v in zip(*lines, strict=True))
        print(
            f"servoL 250 Hz, 5 cm line ({args.runs} runs): final error median {np.median(final):.3f} "
            f"max {final.max():.3f} mm; cross-track max {cross.max():.3f} mm; lag max {lag.max():.2f} mm"
        )
        arm = URArm(emulator.host, URArmOptions(state_timeout_s=0.5))
        timings = {}
        t = time.monotonic()
        arm.connect()
        timings["connect"] = time.monotonic() - t
        t = time.monotonic()
        arm.activate()
        timings["activate"] = time.monotonic() - t
        rng = np.random.default_rng(1)
        fast = [
            protective_stop_latency(emulator, arm, loop=False, rng=rng)
            for _ in range(4 * args.runs)
        ]
        looped = [
            protective_stop_latency(emulator, arm, loop=True, rng=rng) for _ in range(4 * args.runs)
        ]
        for name, values in (("polled", fast), ("125 Hz loop", looped)):
            ms = np.array(values) * 1e3
            print(
                f"protective stop → URArm.state(), {name} ({len(ms)}): median {np.median(ms):.2f} "
                f"p90 {np.percentile(ms, 90):.2f} max {ms.max():.2f} ms"
            )
        pid = emulator.pid
        c0, t0 = _cpu_s(pid), time.monotonic()
        for k in range(250):
            arm.state()
            arm.servo(ServoCommand(time.monotonic(), np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0])))
            time.sleep(max(t0 + (k + 1) * PERIOD - time.monotonic(), 0.0))
        moving = (_cpu_s(pid) - c0) / (time.monotonic() - t0)
        arm.stop()
        t = time.monotonic()
        arm.deactivate()
        timings["deactivate"] = time.monotonic() - t
        c0, t0 = _cpu_s(pid), time.monotonic()
        time.sleep(2.0)
        idle = (_cpu_s(pid) - c0) / (time.monotonic() - t0)
        t = time.monotonic()
        arm.close()
        timings["close"] = time.monotonic() - t
        print("URArm " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in timings.items()))
        print(
            f"emulator CPU: idle with a client {idle * 100:.0f} %, moving at 125 Hz {moving * 100:.0f} % of a core"
        )
        first = emulator.status().command_count
        sent = kick_race(emulator.host)
        records = emulator.commands(first)
        lost = sum(r.source == "lost" and r.name == "speedL" for r in records)
        print(f"speedL then kickWatchdog at once: {lost}/{sent} speedL never read by the script")
        status = emulator.status()
        print(
            f"emulator loop: max lag {status.max_lag_s * 1e3:.1f} ms, {status.skipped_periods} periods skipped"
        )


if __name__ == "__main__":
    main()
