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

from hil.configfile import ConfigError

app = typer.Typer(
    help="satgrasp: vision-guided approach and grasp of a satellite mock-up with a UR arm.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (timings on this machine).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

console = Console(stderr=True)
out = Console()

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
    from hil.config import NoiseConfig

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
    from hil.config import Lighting, RenderConfig, load_camera, load_mockup
    from hil.scenarios import camera_pose_for, target_offset
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
    from hil.bench import render_timings

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
    from drivers.base import Frame
    from estimators.measurement import Measurement, Tracker
    from estimators.registry import build_estimator
    from hil.config import load_camera, load_mockup
    from hil.overlay import draw_measurement

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
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
) -> None:
    """Run the reference study's test matrix against simulator ground truth and print the
    per-case mean ± std of the errors beside the targets and the reference's numbers."""
    from dataclasses import asdict

    from hil.matrix import MatrixSpec, markdown_table, run_matrix, summarize
    from hil.scenarios import MANEUVERS

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
        )
    except ValueError as exc:
        raise _fail(f"bad --distance: {exc}") from None
    for level in spec.noises:
        _noise_config(level)
    try:
        rows = run_matrix(spec, jobs=jobs, progress=lambda text: console.print(text))
    except (ValueError, NotImplementedError) as exc:
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

    from hil.bench import estimator_timings

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
def demo(
    out_dir: Annotated[Path, typer.Option(help="Directory for the demo's outputs.")] = Path("runs"),
) -> None:
    """Run the simulated demo on the embedded default configuration."""
    from hil.demo import run_demo

    run_demo(out_dir, console=out)


def main() -> None:
    try:
        app()
    except ConfigError as exc:  # a configuration named deeper than a command's own checks
        console.print(f"[bold red]error:[/] {exc}")
        sys.exit(2)
