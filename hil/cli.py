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

app = typer.Typer(
    help="satgrasp: vision-guided approach and grasp of a satellite mock-up with a UR arm.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (timings on this machine).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

console = Console(stderr=True, soft_wrap=True)  # never split a path across lines
out = Console(soft_wrap=True)

CameraOpt = Annotated[
    str, typer.Option(help="Camera profile: a built-in name (reference, oak_d_rgb) or a YAML path.")
]
MockupOpt = Annotated[
    str, typer.Option(help="Mock-up: 'default', a YAML path, or random:SEED (a random mock-up).")
]
MockupsOpt = Annotated[
    str,
    typer.Option(
        help="Mock-up(s): 'default', a YAML path, random:SEED, random:A-B (one per seed) or a "
        "comma list of these."
    ),
]
LightOpt = Annotated[
    str,
    typer.Option(
        "--light",
        help="Light: default | harsh (a low side sun with shadows) | random (per mock-up).",
    ),
]
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
    mockup: MockupsOpt = "default",
    light: LightOpt = "default",
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
    per-case mean ± std of the errors beside the targets and the reference's numbers, the
    estimators' biases and (with several mock-ups) a row per mock-up."""
    from dataclasses import asdict

    from configuration.random_mockup import mockup_names
    from hil.evaluation.matrix import (
        MatrixSpec,
        bias_table,
        markdown_table,
        mockup_table,
        run_matrix,
        summarize,
    )
    from hil.evaluation.scenarios import MANEUVERS

    try:
        names = mockup_names(mockup)
    except ValueError as exc:
        raise _fail(f"bad --mockup: {exc}") from None
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
            mockup=names[0],
            mockups=tuple(names) if len(names) > 1 else (),
            lighting=light,
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
    table = markdown_table(summarize(rows)) + "\n" + bias_table(rows)
    if len(names) > 1:
        table += "\n" + mockup_table(rows)
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
    frames: Annotated[int, typer.Option(min=2, help="Frames from the start to 0.5 m.")] = 120,
    noise: NoiseOpt = "low",
    camera: CameraOpt = "reference",
    mockup: MockupsOpt = "default",
    light: LightOpt = "default",
    start_distance: Annotated[
        float, typer.Option(min=0.6, max=6.0, help="Start distance (m).")
    ] = 2.5,
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Write the markdown tables here.")
    ] = None,
) -> None:
    """Open loop: one estimator tracks the target along a scripted approach path (2.5 m →
    0.5 m, re-centring an off-centre, rotated start); print errors by distance and by the
    fraction of the ring in view, and count the frames that claim a pose beyond their own 3σ
    without flagging it ambiguous. (The closed loop is `satgrasp approach`.)"""
    from configuration.random_mockup import mockup_names
    from hil.evaluation.approach_path import (
        ApproachPath,
        markdown_approach,
        markdown_visible,
        run_approach,
    )

    _noise_config(noise)
    try:
        names = mockup_names(mockup)
        path = ApproachPath(start_distance_m=start_distance)
        results = []
        for name in names:
            results += run_approach(
                system,
                frames=frames,
                noise=noise,
                camera=camera,
                mockup=name,
                seed=seed,
                path=path,
                lighting=light,
            )
    except (ConfigError, ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    bins = tuple(sorted({start_distance, 2.5, 2.0, 1.5, 1.0, 0.75, 0.6, 0.49}, reverse=True))
    bins = tuple(b for b in bins if b <= start_distance)
    text = (
        markdown_approach(results, bins)
        + "\n"
        + markdown_visible(results, (1.01, 0.95, 0.9, 0.8, 0.7, 0.6, 0.5, 0.0))
    )
    lost = sum(r.status == "lost" for r in results)
    firsts = {id(r) for r in results if r.index == 0}
    later = [r for r in results if id(r) not in firsts]
    text += (
        f"\n{len(results)} frames ({len(names)} mock-up(s)), {lost} lost, statuses after the "
        "first: "
        + ", ".join(
            f"{s} {sum(r.status == s for r in later)}" for s in ("tracking", "acquired", "lost")
        )
        + f"; flagged ambiguous {sum(r.ambiguous for r in results if r.status != 'lost')}"
        + "; claiming a pose beyond its own 3σ without the flag: "
        + f"{sum(r.overconfident for r in results)} "
        + f"(tracking {sum(r.overconfident for r in results if r.status == 'tracking')})\n"
    )
    out.print(text, markup=False, highlight=False)
    if out_path is not None:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(text, encoding="utf-8")


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
        typer.Option("--out", help="Report directory [default: <log name>_report beside the log]."),
    ] = None,
) -> None:
    """Plots and an HTML page for one trial log: range and phases, errors of each estimator
    and of the fused estimate against ground truth (simulation), measurements accepted /
    rejected / lost, commands, and a summary."""
    from hil.analysis.report import make_report
    from hil.logs.triallog import TrialLogError

    target = out_dir if out_dir is not None else log.with_name(f"{log.stem}_report")
    try:
        index = make_report(log, target)
    except (FileNotFoundError, TrialLogError) as exc:
        raise _fail(str(exc)) from None
    except OSError as exc:
        raise _fail(f"cannot write the report to {target}: {exc}") from None
    out.print(f"report: {index}")


SimOpt = Annotated[
    str, typer.Option("--config", help="Simulation: 'sim' (configs/sim.yaml) or a YAML path.")
]


@bench_app.command("loop")
def bench_loop(
    config: SimOpt = "sim",
    seed: Annotated[int, typer.Option(help="Trial seed.")] = 1,
    duration: Annotated[
        float, typer.Option(help="Simulated seconds of the approach to time.")
    ] = 20.0,
    log_dir: Annotated[Path, typer.Option(help="Where the timed trial's log goes.")] = Path(
        "runs/bench"
    ),
) -> None:
    """Median and p95 of one control tick with a frame (every estimator + fusion + command,
    one thread, camera wait excluded) during a simulated approach."""
    import time as _time

    from hil.analysis.bench import loop_timings

    log_dir.mkdir(parents=True, exist_ok=True)
    log_path = log_dir / f"bench_loop_{_time.strftime('%Y%m%d-%H%M%S')}.mcap"
    try:
        r = loop_timings(config, seed=seed, duration_s=duration, log_path=log_path)
    except (ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    out.print(
        f"ticks with a frame: {r.frame_ticks}, median {r.frame_tick_median_ms:.1f} ms, "
        f"p95 {r.frame_tick_p95_ms:.1f} ms (estimators + fusion + command; camera wait excluded)"
    )
    for system, ms in r.estimator_median_ms.items():
        out.print(f"  {system}: median {ms:.1f} ms")
    out.print(f"  fusion: median {r.fusion_median_ms:.2f} ms")
    out.print(f"ticks without a frame: {r.other_ticks}, median {r.other_tick_median_ms:.2f} ms")
    out.print(f"camera read (simulation: rendering): median {r.camera_read_median_ms:.1f} ms")
    out.print(f"log: {log_path}")


def _simulation(config: str, noise: str | None, systems: str | None, links: str | None):
    from configuration.simulation import load_simulation
    from hil.runtime.trial import with_overrides

    if noise is not None:
        _noise_config(noise)
    try:
        sim = load_simulation(config)
        return with_overrides(
            sim,
            noise={"preset": noise} if noise else None,
            systems=systems.split(",") if systems else None,
            links=links,
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
    log_dir: Annotated[Path, typer.Option(help="Directory for the trial log.")] = Path("runs"),
    report_too: Annotated[
        bool, typer.Option("--report/--no-report", help="Write the report after the trial.")
    ] = True,
) -> None:
    """Run one simulated approach (2.5 m → 0.5 m stand-off, grasp, retreat) with a live
    progress line; write its trial log (MCAP) and, by default, its report."""
    import time

    from rich.live import Live

    from hil.progress import tick_line
    from hil.runtime.trial import run_sim_trial

    sim = _simulation(config, noise, systems, links)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    log_path = log_dir / f"approach_{sim.noise.preset}_seed{seed}_{stamp}.mcap"
    out.print(
        f"simulated approach: systems {', '.join(sim.systems)}, noise {sim.noise.preset}, seed {seed}"
    )
    last_shown = [-1.0]
    with Live("", console=console, refresh_per_second=8, transient=False) as live:

        def on_tick(record: dict) -> None:
            if record["t"] - last_shown[0] >= 0.25 or record["phase"] in ("done", "abort"):
                last_shown[0] = record["t"]
                live.update(tick_line(record))

        try:
            result = run_sim_trial(sim, seed=seed, log_path=log_path, on_tick=on_tick)
        except (ValueError, NotImplementedError) as exc:
            raise _fail(str(exc)) from None
    console.print()  # end the live line
    o = result.outcome
    verdict = "[bold green]SUCCESS[/]" if o.success else "[bold red]FAILURE[/]"
    out.print(
        f"{verdict}: ended in {o.phase} after {o.duration_s:.1f} s simulated ({o.ticks} ticks)"
    )
    if o.abort_reason:
        out.print(f"abort reason: {o.abort_reason}")
    if o.standoff_error_m is not None:
        import math

        out.print(
            f"true camera error at the stand-off: {1000 * o.standoff_error_m:.2f} mm, "
            f"{math.degrees(o.standoff_error_rad):.3f}° (success needs ≤ "
            f"{1000 * sim.approach.standoff.success_position_m:.0f} mm and "
            f"{sim.approach.standoff.success_angle_deg}°)"
        )
    out.print(f"trial log: {log_path}")
    if report_too:
        from hil.analysis.report import make_report

        index = make_report(log_path, log_path.with_name(log_path.stem + "_report"))
        out.print(f"report: {index}")
    raise typer.Exit(code=0 if o.success else 1)


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
    sim = _simulation(config, None, systems, None)

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
    the measurements and ground truth in simulated trial logs, so that the NEES is honest from
    near to far; prints the `fusion:` settings for a simulation config."""
    import math

    import numpy as np
    import yaml

    from estimators.geometry import Pose
    from estimators.measurement import Measurement
    from hil.analysis.calibration import fit_scale_and_floor
    from hil.analysis.trial_analysis import target_from_header
    from hil.logs.triallog import TrialLog, TrialLogError

    samples, target = [], None
    for path in logs:
        try:
            log = TrialLog.open(path)
        except (TrialLogError, OSError) as exc:
            raise _fail(str(exc)) from None
        target = target or target_from_header(log.header)
        for tick in log.ticks():
            truth = (tick.get("truth") or {}).get("X_CT")
            if truth is None:
                continue
            X_CT_true = Pose.from_matrix(np.array(truth), orthonormalize=True)
            for record in tick.get("measurements") or []:
                m = Measurement.from_dict(record)
                if m.valid:
                    samples.append((m, X_CT_true))
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
        log_dir=out_dir,
        report_too=True,
    )


def main() -> None:
    try:
        app()
    except ConfigError as exc:  # a configuration named deeper than a command's own checks
        console.print(f"[bold red]error:[/] {exc}")
        sys.exit(2)
