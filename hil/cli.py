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
