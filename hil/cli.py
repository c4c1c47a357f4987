"""The ``satgrasp`` command line. Command functions are thin: they parse options, call the
library and print; errors in user input exit with status 2 and a one-line reason."""

from __future__ import annotations

import json
import sys
from importlib.metadata import version
from pathlib import Path
from typing import Annotated

import cv2
import numpy as np
import typer
from rich.console import Console

from configuration.files import ConfigError
from hil.cli_emulate import emulate_app
from hil.cli_rig import check_rig

app = typer.Typer(
    help="satgrasp: vision-guided approach and grasp of a satellite mock-up with a UR arm.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (timings on this machine).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
app.add_typer(emulate_app, name="emulate")
app.command("check-rig")(check_rig)

console = Console(stderr=True, soft_wrap=True)  # never split a path across lines
out = Console(soft_wrap=True)

CameraOpt = Annotated[
    str, typer.Option(help="Camera profile: a built-in name (reference, oak_d_rgb) or a YAML path.")
]
MockupOpt = Annotated[str, typer.Option(help="Mock-up: 'default' or a YAML path.")]
NoiseOpt = Annotated[
    str,
    typer.Option(help="Image noise: none | low | high (reference variances 0/0.05/0.1) | sensor."),
]


def _fail(message: str) -> typer.Exit:
    console.print(f"[bold red]error:[/] {message}")
    return typer.Exit(code=2)


def _version_callback(value: bool) -> None:
    if value:
        out.print(f"satgrasp {version('satgrasp')}")
        raise typer.Exit()


@app.callback()
def _main(
    show_version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version_callback, is_eager=True, help="Print the version."
        ),
    ] = False,
) -> None:
    """Vision-guided approach and grasp of a satellite mock-up."""


def _noise_config(noise: str):
    from configuration.render import NoiseConfig

    if noise not in ("none", "low", "high", "sensor"):
        raise _fail(f"--noise must be none, low, high or sensor; got {noise!r}")
    return NoiseConfig(preset=noise)


@app.command()
def render(
    out_path: Annotated[Path, typer.Option("--out", help="PNG file to write.")] = Path("frame.png"),
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    distance: Annotated[
        float, typer.Option(help="Camera distance in front of the ring face (m).")
    ] = 2.0,
    dx: Annotated[float, typer.Option(help="Target displacement along its x (m).")] = 0.0,
    dy: Annotated[float, typer.Option(help="Target displacement along its y (m).")] = 0.0,
    dz: Annotated[float, typer.Option(help="Target displacement along its z (m).")] = 0.0,
    roll_deg: Annotated[float, typer.Option(help="Target rotation about its x (deg).")] = 0.0,
    pitch_deg: Annotated[float, typer.Option(help="Target rotation about its y (deg).")] = 0.0,
    yaw_deg: Annotated[float, typer.Option(help="Target rotation about its z (deg).")] = 0.0,
    noise: NoiseOpt = "none",
    seed: Annotated[int, typer.Option(help="Noise seed: same seed, identical frame.")] = 0,
    supersample: Annotated[int, typer.Option(min=1, max=4, help="Anti-aliasing factor.")] = 1,
    shadows: Annotated[
        bool, typer.Option(help="Hard shadows from the sun light (slower).")
    ] = False,
    truth: Annotated[
        Path | None, typer.Option(help="JSON file for the ground truth X_CT, K, distortion, size.")
    ] = None,
) -> None:
    """Render one frame of the mock-up with exact ground truth.

    The camera faces the ring from DISTANCE metres; the target is then moved by the offsets and
    rotated by roll/pitch/yaw about its own axes (the reference study's maneuvers).
    """
    from configuration.camera import load_camera
    from configuration.mockup import load_mockup
    from configuration.render import Lighting, RenderConfig
    from hil.evaluation.scenarios import camera_pose_for, target_offset
    from sim_backends.camera import SimCamera, Viewpoint
    from sim_backends.renderer import PybulletRenderer
    from sim_backends.scene import MockupScene

    noise_config = _noise_config(noise)
    if distance <= 0:
        raise _fail(f"--distance must be positive; got {distance}")
    try:
        camera_config = load_camera(camera)
        mockup_config = load_mockup(mockup)
    except ConfigError as exc:
        raise _fail(str(exc)) from None
    offset = target_offset(dx, dy, dz, *np.radians([roll_deg, pitch_deg, yaw_deg]))
    X_WC, X_CT = camera_pose_for(distance, offset)
    if X_CT.p[2] <= 0:
        raise _fail("the target is behind the camera; reduce --dz or increase --distance")
    info = camera_config.camera_info()
    config = RenderConfig(supersample=supersample, lighting=Lighting(shadows=shadows))
    with MockupScene(mockup_config) as scene:
        sim_camera = SimCamera(
            PybulletRenderer(scene, info, config), lambda: Viewpoint(X_WC), noise_config, seed=seed
        )
        sim_camera.connect()
        sim_camera.activate()
        frame = sim_camera.read()
        sim_camera.close()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_path), frame.image):
        raise _fail(f"could not write {out_path}")
    record = {
        "image": str(out_path),
        "camera": info.to_dict(),
        "mockup": mockup_config.name,
        "noise": noise,
        "seed": seed,
        "X_CT": X_CT.to_list(),
    }
    if truth is not None:
        truth.parent.mkdir(parents=True, exist_ok=True)
        truth.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    out.print(
        f"wrote {out_path} ({info.width}x{info.height}, {info.model}, noise {noise}, seed {seed})"
    )
    out.print("X_CT (target in camera, m):")
    out.print(np.array2string(X_CT.matrix, precision=6, suppress_small=True))


@bench_app.command("render")
def bench_render(
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    repeats: Annotated[int, typer.Option(min=1, help="Frames timed per case.")] = 9,
) -> None:
    """Median and p95 render time per frame at 3, 2, 1.2 and 0.5 m, with and without 2×
    supersampling (one thread, noise included)."""
    from hil.analysis.bench import render_timings

    try:
        rows = render_timings(camera, mockup, repeats=repeats, progress=console)
    except ConfigError as exc:
        raise _fail(str(exc)) from None
    from rich.table import Table

    table = Table(title=f"render time per frame, camera {camera}")
    for column in ("distance (m)", "supersample", "median (ms)", "p95 (ms)"):
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(
            f"{row.distance_m:.1f}",
            str(row.supersample),
            f"{row.median_ms:.1f}",
            f"{row.p95_ms:.1f}",
        )
    out.print(table)


@app.command()
def estimate(
    images: Annotated[list[Path], typer.Argument(help="Image files (PNG, JPEG, …).")],
    system: Annotated[str, typer.Option(help="Estimator: corners | lines | ellipses.")] = "corners",
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    track: Annotated[
        bool, typer.Option(help="Carry the pose from image to image as the prior.")
    ] = False,
    overlay: Annotated[
        Path | None, typer.Option(help="Directory for overlay images (features, labels, model).")
    ] = None,
) -> None:
    """Estimate the target's pose in each image; one JSON line per image on stdout.

    Keys: image, system, status (acquired | tracking | lost), reason, X_CT (4×4 or null),
    covariance, residual_px, time_ms; 5-DOF circle poses add circle, center_C, normal_C.
    """
    from configuration.camera import load_camera
    from configuration.mockup import load_mockup
    from estimators.frame import Frame
    from estimators.measurement import Measurement, Tracker
    from estimators.registry import build_estimator
    from hil.evaluation.overlay import draw_measurement

    try:
        info = load_camera(camera).camera_info()
        target = load_mockup(mockup).target_model()
        estimator = build_estimator(system, target, info)
    except (ConfigError, ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    tracker = Tracker(estimator)
    if overlay is not None:
        overlay.mkdir(parents=True, exist_ok=True)
    flag = cv2.IMREAD_GRAYSCALE if info.channels == 1 else cv2.IMREAD_COLOR
    for seq, path in enumerate(images):
        image = cv2.imread(str(path), flag)
        if image is None:
            frame = Frame(np.zeros((0, 0), np.uint8), float(seq), info, seq)
            m = Measurement.lost(system, frame, f"cannot read image {path}")
        else:
            if not track:
                tracker.reset()
            m = tracker.update(Frame(image, float(seq), info, seq))
        print(json.dumps({"image": str(path), **m.to_dict()}), flush=True)
        if overlay is not None and image is not None:
            cv2.imwrite(
                str(overlay / f"{path.stem}_{system}.png"), draw_measurement(image, m, info, target)
            )


@app.command()
def matrix(
    system: Annotated[list[str], typer.Option(help="Estimator(s); repeat the option for several.")],
    frames: Annotated[int, typer.Option(min=2, help="Frames per case (one maneuver period).")] = 30,
    noise: Annotated[str, typer.Option(help="Comma-separated noise levels.")] = "none,low,high",
    distance: Annotated[str, typer.Option(help="Comma-separated distances (m).")] = "3,2,1.2",
    maneuver: Annotated[str, typer.Option(help="Comma-separated maneuvers, or 'all'.")] = "all",
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    blank: Annotated[
        str, typer.Option(help="Comma-separated frame indices replaced by blank frames.")
    ] = "",
    jobs: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 1,
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Write the markdown table here.")
    ] = None,
    results: Annotated[
        Path | None, typer.Option(help="Write every frame's result as JSON lines.")
    ] = None,
    supersample: Annotated[
        int, typer.Option(min=1, max=4, help="Render anti-aliasing factor (pixel-area sampling).")
    ] = 1,
    acquisition: Annotated[
        bool, typer.Option(help="Also estimate every frame without a prior (acquisition rate).")
    ] = False,
) -> None:
    """Run the reference study's test matrix against simulator ground truth and print the
    per-case mean ± std of the errors beside the targets and the reference's numbers."""
    from dataclasses import asdict

    from hil.evaluation.matrix import MatrixSpec, markdown_table, run_matrix, summarize
    from hil.evaluation.scenarios import MANEUVERS

    try:
        spec = MatrixSpec(
            systems=tuple(system),
            distances_m=tuple(float(d) for d in distance.split(",")),
            maneuvers=tuple(m.name for m in MANEUVERS)
            if maneuver == "all"
            else tuple(maneuver.split(",")),
            noises=tuple(noise.split(",")),
            frames=frames,
            seed=seed,
            supersample=supersample,
            acquisition=acquisition,
            camera=camera,
            mockup=mockup,
            blank_frames=tuple(int(i) for i in blank.split(",") if i.strip()),
        )
    except ValueError as exc:
        raise _fail(f"bad --distance or --blank: {exc}") from None
    for level in spec.noises:
        _noise_config(level)
    try:
        rows = run_matrix(spec, jobs=jobs, progress=lambda text: console.print(text))
    except (ValueError, NotImplementedError, ConfigError) as exc:
        raise _fail(str(exc)) from None
    table = markdown_table(summarize(rows))
    out.print(table, markup=False, highlight=False, soft_wrap=True)
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(table, encoding="utf-8")
    if results is not None:
        results.parent.mkdir(parents=True, exist_ok=True)
        with results.open("w", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(asdict(row), allow_nan=True) + "\n")


@app.command("path")
def approach_path(
    system: Annotated[str, typer.Option(help="Estimator: corners | lines | ellipses.")],
    frames: Annotated[int, typer.Option(min=2, help="Frames from 2.5 m to 0.5 m.")] = 120,
    noise: NoiseOpt = "low",
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Write the markdown tables here.")
    ] = None,
) -> None:
    """Open loop: one estimator tracks the target along a scripted approach path (2.5 m →
    0.5 m, re-centring an off-centre, rotated start); print errors by distance and by the
    fraction of the ring in view. (The closed loop is `satgrasp approach`.)"""
    from hil.evaluation.approach_path import markdown_approach, markdown_visible, run_approach

    _noise_config(noise)
    try:
        results = run_approach(
            system, frames=frames, noise=noise, camera=camera, mockup=mockup, seed=seed
        )
    except (ConfigError, ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    text = (
        markdown_approach(results, (2.5, 2.0, 1.5, 1.0, 0.75, 0.6, 0.49))
        + "\n"
        + markdown_visible(results, (1.01, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5, 0.0))
    )
    lost = sum(r.status == "lost" for r in results)
    text += (
        f"\n{len(results)} frames, {lost} lost, statuses after the first: "
        + ", ".join(
            f"{s} {sum(r.status == s for r in results[1:])}"
            for s in ("tracking", "acquired", "lost")
        )
        + "\n"
    )
    out.print(text, markup=False, highlight=False)
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(text, encoding="utf-8")


@app.command()
def record(
    out_dir: Annotated[Path, typer.Option("--out", help="Directory for the recording.")],
    frames: Annotated[int, typer.Option(min=2, help="Frames from 2.5 m to 0.5 m.")] = 120,
    noise: NoiseOpt = "low",
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    codec: Annotated[str, typer.Option(help="Video codec: ffv1 (lossless) | mjpg.")] = "ffv1",
    jpeg_quality: Annotated[int, typer.Option(min=1, max=100, help="MJPG quality.")] = 100,
    check: Annotated[
        bool, typer.Option(help="Replay it through the OAK driver and compare the poses.")
    ] = False,
) -> None:
    """Save the open-loop approach path as an OAK recording: video, depthai calibration JSON,
    ground truth (JSON lines). With --check, replay it through the OAK driver and print each
    estimator's poses on the replayed frames against the truth and the direct frames, and the
    replay's pacing and latency."""
    from drivers.base import DeviceError
    from hil.evaluation import recording as rec

    _noise_config(noise)
    options = dict(frames=frames, noise=noise, camera=camera, mockup=mockup, seed=seed, codec=codec)
    options["jpeg_quality"] = jpeg_quality
    try:
        if check:
            result = rec.record_and_check(out_dir, **options)
            text = rec.markdown_comparison(result.comparison)
            text += "\n" + rec.replay_timing(result.recording).text() + "\n"
            out.print(text, markup=False, highlight=False)
        else:
            rec.record_approach(out_dir, **options)
    except (ConfigError, ValueError, OSError, DeviceError) as exc:
        raise _fail(str(exc)) from None
    out.print(f"recording in {out_dir}", markup=False, highlight=False)


@bench_app.command("estimate")
def bench_estimate(
    system: Annotated[list[str], typer.Option(help="Estimator(s); repeat for several.")],
    camera: CameraOpt = "reference",
    frames: Annotated[int, typer.Option(min=2, help="Frames per distance.")] = 20,
    noise: NoiseOpt = "low",
) -> None:
    """Median and p95 time per frame of each estimator (one thread), tracking and acquisition
    separately, at 3, 2 and 1.2 m."""
    from rich.table import Table

    from hil.analysis.bench import estimator_timings

    _noise_config(noise)
    try:
        rows = estimator_timings(
            tuple(system), camera=camera, frames=frames, noise=noise, progress=console
        )
    except (ConfigError, ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    table = Table(title=f"estimator time per frame ({camera}, noise {noise}, one thread)")
    for column in ("system", "mode", "distance (m)", "median (ms)", "p95 (ms)", "valid"):
        table.add_column(column, justify="right")
    for r in rows:
        table.add_row(
            r.system,
            r.mode,
            f"{r.distance_m:.1f}",
            f"{r.median_ms:.1f}",
            f"{r.p95_ms:.1f}",
            f"{r.valid}/{r.frames}",
        )
    out.print(table)


@app.command()
def report(
    log: Annotated[Path, typer.Argument(help="Trial log (.mcap), complete or cut off by a crash.")],
    out_dir: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Report directory [default: <log name>_report beside the log; with --json, "
            "none unless given].",
        ),
    ] = None,
    as_json: Annotated[
        bool,
        typer.Option(
            "--json",
            help="Print the trial's figures as one JSON object on stdout (outcome, timing, "
            "frames, vision latency, stand-off error, per-system results).",
        ),
    ] = False,
) -> None:
    """Plots and an HTML page for one trial log: range and phases, errors of each estimator
    and of the fused estimate against ground truth (simulation), estimator results accepted /
    rejected / lost / stale, commands, control-loop timing and vision latency, and a summary.
    With --json, the same figures as one JSON object (docs/trial_logs.md lists the keys)."""
    from hil.analysis.report import report_json, write_report
    from hil.analysis.trial_analysis import analyse
    from hil.logs.triallog import TrialLog, TrialLogError

    try:
        analysis = analyse(TrialLog.open(log))
    except (FileNotFoundError, TrialLogError) as exc:
        raise _fail(str(exc)) from None
    if as_json:
        typer.echo(json.dumps(report_json(analysis), indent=2, allow_nan=False))
        if analysis.incomplete:
            console.print(f"[yellow]warning:[/] {log} is incomplete: {analysis.incomplete}")
        if out_dir is None:
            return
    target = out_dir if out_dir is not None else log.with_name(f"{log.stem}_report")
    try:
        index = write_report(analysis, target)
    except OSError as exc:
        raise _fail(f"cannot write the report to {target}: {exc}") from None
    if as_json:
        console.print(f"report: {index}")
    else:
        out.print(f"report: {index}")


SimOpt = Annotated[
    str, typer.Option("--config", help="Simulation: 'sim' (configs/sim.yaml) or a YAML path.")
]


@bench_app.command("loop")
def bench_loop(
    config: SimOpt = "sim",
    ticks: Annotated[int, typer.Option(min=100, help="Control ticks timed.")] = 2000,
    seconds: Annotated[
        float, typer.Option(min=2.0, help="Seconds each vision pipeline runs.")
    ] = 20.0,
    fps: Annotated[float, typer.Option(min=1.0, help="Camera frame rate fed to vision.")] = 30.0,
    camera: CameraOpt = "reference",
) -> None:
    """The two rates on this machine: the control tick without vision (wall time, p50/p99/max
    against the period), and the vision pipeline's throughput and latency with the three
    systems serial (one process) and concurrent (a process each), side by side."""
    from rich.table import Table

    from hil.analysis.bench_loop import approach_frames, control_tick_timing, pipeline_timing

    try:
        tick = control_tick_timing(config, ticks=ticks)
    except (ValueError, ConfigError) as exc:
        raise _fail(str(exc)) from None
    out.print(
        f"control tick without vision ({tick.ticks} ticks, period {tick.period_ms:.1f} ms): "
        f"p50 {tick.p50_ms:.2f} ms, p99 {tick.p99_ms:.2f} ms, max {tick.max_ms:.2f} ms"
    )
    systems = ("corners", "lines", "ellipses")
    console.print("rendering an approach from 3 m to 0.5 m …")
    frames = approach_frames(camera, "default", frames=24)
    rows = [
        pipeline_timing(mode, frames, systems, fps=fps, seconds=seconds, progress=console.print)
        for mode in ("serial", "concurrent")
    ]
    table = Table(title=f"vision pipeline, camera at {fps:.0f} fps, {seconds:.0f} s each")
    for column in ("mode", "frames/s (all systems)", *systems, "latency p50 (ms)", "p95 (ms)"):
        table.add_column(column, justify="right")
    for r in rows:
        table.add_row(
            r.mode,
            f"{r.frames_per_s:.1f}",
            *(f"{r.results_per_s[s]:.1f}/s" for s in systems),
            f"{r.latency_p50_ms:.0f}",
            f"{r.latency_p95_ms:.0f}",
        )
    out.print(table)
    ratio = rows[1].frames_per_s / rows[0].frames_per_s if rows[0].frames_per_s else float("nan")
    out.print(f"concurrent / serial throughput: {ratio:.2f}×")


SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Override a config value, KEY=VALUE with a dotted key (repeatable), e.g. "
        "--set vision.fuse_at=arrival --set camera_timing.latency_s=0.1.",
    ),
]


def _simulation(
    config: str,
    noise: str | None,
    systems: str | None,
    links: str | None,
    clock: str | None = None,
    settings: list[str] | None = None,
):
    from configuration.simulation import load_simulation, with_overrides, with_settings

    if noise is not None:
        _noise_config(noise)
    if clock is not None and clock not in ("sim", "wall"):
        raise _fail(f"--clock must be sim or wall; got {clock!r}")
    try:
        sim = with_settings(load_simulation(config), settings or [])
        return with_overrides(
            sim,
            noise={"preset": noise} if noise else None,
            systems=systems.split(",") if systems else None,
            links=links,
            clock=clock,
        )
    except ValueError as exc:  # ConfigError or a validation error of an override
        raise _fail(str(exc)) from None


@app.command()
def approach(
    config: SimOpt = "sim",
    noise: Annotated[
        str | None, typer.Option(help="Override the noise: none | low | high | sensor.")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the random start and the image noise.")] = 1,
    systems: Annotated[
        str | None, typer.Option(help="Comma-separated estimators, e.g. corners,lines,ellipses.")
    ] = None,
    links: Annotated[
        str | None, typer.Option(help="direct | tcp (track and gripper over pymodbus).")
    ] = None,
    clock: Annotated[
        str | None,
        typer.Option(
            help="sim: stepped as fast as possible with vision time charged (deterministic); "
            "wall: the simulated world runs in real time in its own processes, like a rig. "
            "[default: the config's, sim]"
        ),
    ] = None,
    settings: SetOpt = None,
    log_dir: Annotated[Path, typer.Option(help="Directory for the trial log.")] = Path("runs"),
    report_too: Annotated[
        bool, typer.Option("--report/--no-report", help="Write the report after the trial.")
    ] = True,
) -> None:
    """Run one approach (2.5 m → 0.5 m stand-off, grasp, retreat) with a live progress line;
    write its trial log (MCAP) and, by default, its report. Simulated by default; the config's
    devices: section may name the real drivers against emulators (emulated) or the rig."""
    import time

    from rich.live import Live

    from drivers.base import DeviceError
    from hil.progress import tick_line
    from hil.runtime.compose import run_trial
    from hil.runtime.processes import ProcessStartError

    sim = _simulation(config, noise, systems, links, clock, settings)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    log_path = log_dir / f"approach_{sim.noise.preset}_seed{seed}_{stamp}.mcap"
    out.print(
        f"{sim.devices.kind} approach: systems {', '.join(sim.systems)}, noise {sim.noise.preset}, "
        f"seed {seed}, clock {sim.clock}"
    )
    last_shown = [-1.0]
    with Live("", console=console, refresh_per_second=8, transient=False) as live:

        def on_tick(record) -> None:
            if record.t - last_shown[0] >= 0.25 or record.phase in ("done", "abort"):
                last_shown[0] = record.t
                live.update(tick_line(record))

        try:
            result = run_trial(sim, seed=seed, log_path=log_path, on_tick=on_tick)
        except (ValueError, NotImplementedError, DeviceError, ProcessStartError) as exc:
            raise _fail(str(exc)) from None  # a device or emulator that did not start: why
    console.print()  # end the live line
    o = result.outcome
    verdict = "[bold green]SUCCESS[/]" if result.success else "[bold red]FAILURE[/]"
    kind = "simulated" if result.clock == "sim" else "on the wall clock"
    out.print(
        f"{verdict}: ended in {o.phase} after {o.duration_s:.1f} s {kind} ({o.ticks} ticks, "
        f"{o.deadline_misses} deadline misses)"
    )
    if o.abort_reason:
        out.print(f"abort reason: {o.abort_reason}")
    if result.standoff_error_m is not None:
        import math

        out.print(
            f"true camera error at the stand-off: {1000 * result.standoff_error_m:.2f} mm, "
            f"{math.degrees(result.standoff_error_rad):.3f}° (success needs ≤ "
            f"{1000 * sim.approach.standoff.success_position_m:.0f} mm and "
            f"{sim.approach.standoff.success_angle_deg}°)"
        )
    out.print(f"trial log: {log_path}")
    if report_too:
        from hil.analysis.report import make_report

        index = make_report(log_path, log_path.with_name(log_path.stem + "_report"))
        out.print(f"report: {index}")
    raise typer.Exit(code=0 if result.success else 1)


@app.command()
def campaign(
    config: SimOpt = "sim",
    seeds: Annotated[
        int, typer.Option(min=1, help="Trials per noise level (seeds S..S+N-1).")
    ] = 20,
    first_seed: Annotated[
        int,
        typer.Option(
            min=0,
            help="First seed S; e.g. calibrate on seeds 101.. and evaluate on 1.. to keep "
            "them apart.",
        ),
    ] = 1,
    noise: Annotated[str, typer.Option(help="Comma-separated noise levels.")] = "low,high",
    systems: Annotated[str | None, typer.Option(help="Comma-separated estimators.")] = None,
    jobs: Annotated[int, typer.Option(min=1, help="Trials run at once (processes).")] = 1,
    settings: SetOpt = None,
    out_dir: Annotated[Path, typer.Option(help="Directory for the logs and the summary.")] = Path(
        "runs/campaign"
    ),
) -> None:
    """Run many simulated approaches (random starts as in the reference: 2.5 m, ±0.3 m off
    centre, ±10° rotated) and summarise success and errors from their logs."""
    from hil.analysis.campaign import campaign_markdown, run_campaign

    levels = noise.split(",")
    for level in levels:
        _noise_config(level)
    sim = _simulation(config, None, systems, None, None, settings)

    def progress(row, done, total) -> None:
        verdict = "ok  " if row.success else "FAIL"
        console.print(
            f"[{done}/{total}] {verdict} noise {row.noise} seed {row.seed}: {row.phase} "
            f"{row.abort_reason}".rstrip()
        )

    rows = run_campaign(
        sim, range(first_seed, first_seed + seeds), levels, out_dir, jobs=jobs, progress=progress
    )
    table = campaign_markdown(rows)
    (out_dir / "summary.md").write_text(table, encoding="utf-8")
    out.print(table, markup=False, highlight=False)
    out.print(f"summary: {out_dir / 'summary.md'}")


@app.command()
def calibrate(
    logs: Annotated[list[Path], typer.Argument(help="Trial logs (MCAP) of simulated runs.")],
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Write the fusion settings (YAML) here.")
    ] = None,
) -> None:
    """Fit each estimator's covariance calibration (scale × stated + model-error floor) from
    the measurements in simulated trial logs and the truth at their frames' capture, so that
    the NEES is honest from near to far; prints the `fusion:` settings for a simulation
    config."""
    import math

    import yaml

    from hil.analysis.calibration import fit_scale_and_floor, samples_with_truth
    from hil.analysis.trial_analysis import target_from_header
    from hil.logs.triallog import TrialLog, TrialLogError

    samples, target = [], None
    for path in logs:
        try:
            log = TrialLog.open(path)
        except (TrialLogError, OSError) as exc:
            raise _fail(str(exc)) from None
        target = target or target_from_header(log.header)
        samples += samples_with_truth(log.vision())
    if target is None or not samples:
        raise _fail("no measurements with ground truth in these logs (simulated runs needed)")
    result = fit_scale_and_floor(samples, target)
    for c in result.values():
        out.print(
            f"{c.system}: scale {c.scale:.2f}, floor {1000 * c.floor[1]:.2f} mm / "
            f"{math.degrees(c.floor[0]):.3f}°"
        )
        for edge, count, before, after in c.bins:
            out.print(
                f"  range ≤ {edge:.1f} m: {count} measurements, NEES/dof {before:.2f} → {after:.2f}"
            )
    settings = {
        "fusion": {
            "covariance_scale": {c.system: round(c.scale, 3) for c in result.values()},
            "covariance_floor": {
                c.system: [round(c.floor[0], 6), round(c.floor[1], 6)] for c in result.values()
            },
        }
    }
    text = yaml.safe_dump(settings, sort_keys=False)
    out.print(text, markup=False, highlight=False)
    if out_path is not None:
        out_path.write_text(text, encoding="utf-8")


@app.command()
def demo(
    out_dir: Annotated[
        Path, typer.Option(help="Directory for the trial log and its report.")
    ] = Path("runs"),
) -> None:
    """The simulated demo on the embedded default configuration (configs/sim.yaml): one full
    approach with low noise — 2.5 m start, stand-off, grasp, retreat — its trial log and report."""
    approach(
        config="sim",
        noise="low",
        seed=1,
        systems=None,
        links=None,
        clock=None,
        settings=None,
        log_dir=out_dir,
        report_too=True,
    )


def main() -> None:
    try:
        app()
    except ConfigError as exc:  # a configuration named deeper than a command's own checks
        console.print(f"[bold red]error:[/] {exc}")
        sys.exit(2)
