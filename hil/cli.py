"""The ``satgrasp`` command line. Command functions are thin: they parse options, call the
library and print; errors in user input exit with status 2 and a one-line reason — the same
line whether the command's own checks or the option parser found the problem."""

from __future__ import annotations

import contextlib
import enum
import json
import os
import sys
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path
from typing import Annotated, Any, get_args

import cv2
import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup

from configuration.files import ConfigError
from configuration.render import NoiseConfig
from configuration.simulation import ClockKind, LinkKind
from hil import cli_campaigns
from hil.cli_emulate import emulate_app
from hil.cli_faults import faults_command
from hil.cli_rig import check_rig
from hil.runtime.processes import keep_freed_memory

#: The option parser's error type (click's, vendored by recent typer releases).
_ParserError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class _OneLineErrors(TyperGroup):
    """The option parser's errors (a value not among an option's choices, not a number, an
    unknown option) as one line, like every error the commands report themselves, instead of
    a usage line and a framed panel."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except _ParserError as exc:
            if type(exc).__name__ != "NoArgsIsHelpError":  # that one has printed the help
                context = getattr(exc, "ctx", None)
                hint = f" (see {context.command_path} --help)" if context else ""
                message = exc.format_message().replace("Value error, ", "")
                console.print(f"[bold red]error:[/] {escape(message)}{hint}")
            sys.exit(exc.exit_code)
        except typer.Abort:
            console.print("aborted")
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)


app = typer.Typer(
    cls=_OneLineErrors,
    help="satgrasp: vision-guided approach and grasp of a satellite mock-up with a UR arm.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks (timings on this machine).", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
app.add_typer(emulate_app, name="emulate")
app.command("faults")(faults_command)
app.command()(cli_campaigns.crb)
app.command()(cli_campaigns.recover)
app.command()(cli_campaigns.compare)
app.command()(cli_campaigns.video)
app.command("check-rig")(check_rig)

console = Console(stderr=True, soft_wrap=True)  # never split a path across lines
out = Console(soft_wrap=True)


def _choices(name: str, values: tuple[str, ...]) -> Any:
    """An option type taking one of ``values`` (a configuration's ``Literal``, so the names
    live in one place): ``--help`` lists them and any other value gets the parser's one-line
    error. The command reads the chosen name as ``.value``."""
    return enum.Enum(name, {value: value for value in values}, type=str)


Noise = _choices("Noise", get_args(NoiseConfig.model_fields["preset"].annotation))
Clock = _choices("Clock", get_args(ClockKind))
Links = _choices("Links", get_args(LinkKind))
#: ``satgrasp record``'s codecs (``hil.evaluation.recording.CODECS``, which loads the renderer:
#: too slow to import for every command; a test keeps the two the same).
CODEC_NAMES = ("ffv1", "mjpg")
Codec = _choices("Codec", CODEC_NAMES)

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
AutoExposureOpt = Annotated[
    bool,
    typer.Option(
        help="The camera's auto-exposure: each frame scaled, before its noise, so the mock-up's "
        "brightest pixels reach 0.9 of full scale (gain 1/8-8x). Off: as the light makes them."
    ),
]
NoiseOpt = Annotated[
    Noise,
    typer.Option(help="Image noise: reference variances 0 / 0.05 / 0.1, or the sensor model."),
]
SupersampleOpt = Annotated[
    int,
    typer.Option(
        min=1,
        max=4,
        help="Samples per pixel side, averaged (pixel-area sampling, as a sensor integrates "
        "light). 1 samples pixel centres: edges along the pixel grid, as at the head-on "
        "pose, snap to whole pixels (docs/reference_study.md).",
    ),
]


def _fail(message: str, code: int = 2) -> typer.Exit:
    console.print(f"[bold red]error:[/] {escape(message)}")
    return typer.Exit(code=code)


def _output_dir(path: Path, option: str, what: str = "") -> Path:
    """The directory a command will write into, created now, before any work: a path that
    cannot be one is refused in one line naming the option."""
    what = what or f"{option} {path}"
    if path.exists() and not path.is_dir():
        raise _fail(f"{what}: {path} is a file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _fail(f"{what}: cannot create the directory {path} ({exc.strerror or exc})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise _fail(f"{what}: the directory {path} is not writable")
    return path


def _output_file(path: Path, option: str) -> Path:
    """A file a command will write: not a directory, its directory created now."""
    if path.is_dir():
        raise _fail(f"{option} {path}: is a directory; give a file name")
    _output_dir(path.parent, option, what=f"{option} {path}")
    return path


@contextlib.contextmanager
def _writing(path: Path, option: str) -> Iterator[None]:
    """Writing ``path``: an OS error (disk full, permissions) becomes one line naming it."""
    try:
        yield
    except OSError as exc:
        raise _fail(f"{option} {path}: cannot write ({exc.strerror or exc})") from None


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


def _not_a_choice(option: str, value: str, choices: Any) -> typer.BadParameter:
    """The option parser's own error for a value outside ``choices`` (for options that take a
    comma-separated list, which the parser cannot check)."""
    listed = ", ".join(repr(c.value) for c in choices)
    return typer.BadParameter(f"{value!r} is not one of {listed}.", param_hint=f"'{option}'")


def _noise_levels(text: str) -> list[str]:
    """``--noise low,high`` → the levels, each one checked."""
    levels = text.split(",")
    for level in levels:
        if level not in Noise.__members__:
            raise _not_a_choice("--noise", level, Noise)
    return levels


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
    noise: NoiseOpt = Noise.none,
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
    from sim_backends.renderer import make_renderer
    from sim_backends.scene import MockupScene

    noise_config = NoiseConfig(preset=noise.value)
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
    _output_file(out_path, "--out")
    if truth is not None:
        _output_file(truth, "--truth")
    info = camera_config.camera_info()
    config = RenderConfig(supersample=supersample, lighting=Lighting(shadows=shadows))
    with MockupScene(mockup_config) as scene:
        sim_camera = SimCamera(
            make_renderer(scene, info, config), lambda: Viewpoint(X_WC), noise_config, seed=seed
        )
        sim_camera.connect()
        sim_camera.activate()
        frame = sim_camera.read()
        sim_camera.close()
    with _writing(out_path, "--out"):
        if not cv2.imwrite(str(out_path), frame.image):
            raise _fail(
                f"--out {out_path}: OpenCV could not write it (is the suffix an image type?)"
            )
    record = {
        "image": str(out_path),
        "camera": info.to_dict(),
        "mockup": mockup_config.name,
        "noise": noise.value,
        "seed": seed,
        "X_CT": X_CT.to_list(),
    }
    if truth is not None:
        with _writing(truth, "--truth"):
            truth.write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    out.print(
        f"wrote {out_path} ({info.width}x{info.height}, {info.model}, noise {noise.value}, "
        f"seed {seed})"
    )
    out.print("X_CT (target in camera, m):")
    out.print(np.array2string(X_CT.matrix, precision=6, suppress_small=True))


@bench_app.command("render")
def bench_render(
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    repeats: Annotated[int, typer.Option(min=1, help="Frames timed per case.")] = 9,
) -> None:
    """Median and p95 render time per frame at 3, 2, 1.2 and 0.5 m, for each render engine,
    with and without 2× supersampling (one thread, noise included)."""
    from hil.analysis.bench import render_timings

    try:
        rows = render_timings(camera, mockup, repeats=repeats, progress=console)
    except ConfigError as exc:
        raise _fail(str(exc)) from None
    from rich.table import Table

    table = Table(title=f"render time per frame, camera {camera}")
    for column in ("engine", "distance (m)", "supersample", "median (ms)", "p95 (ms)"):
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(
            row.engine,
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
        _output_dir(overlay, "--overlay")
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
            drawn = overlay / f"{path.stem}_{system}.png"
            with _writing(drawn, "--overlay"):
                if not cv2.imwrite(str(drawn), draw_measurement(image, m, info, target)):
                    raise _fail(f"--overlay {overlay}: OpenCV could not write {drawn}")


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
    supersample: SupersampleOpt = 4,
    passes: Annotated[
        int,
        typer.Option(
            min=1,
            max=4,
            help="Renders averaged per frame, their samples shifted by 1/passes of a sample: "
            "square-on edges, which the sample grid places to 1/supersample px, go to "
            "1/(supersample·passes) px, at passes × the render time.",
        ),
    ] = 1,
    acquisition: Annotated[
        bool, typer.Option(help="Also estimate every frame without a prior (acquisition rate).")
    ] = False,
    auto_exposure: AutoExposureOpt = False,
) -> None:
    """Run the reference study's test matrix against simulator ground truth and print the
    per-case mean ± std of the errors beside the targets and the reference's numbers, the
    estimators' biases, (with several mock-ups) a row per mock-up and why frames were lost."""
    from dataclasses import asdict

    from configuration.random_mockup import mockup_names
    from hil.analysis.campaigns.matrix_runs import run_matrix_campaign
    from hil.evaluation.matrix import (
        MatrixSpec,
        bias_table,
        loss_table,
        markdown_table,
        mockup_table,
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
            noises=tuple(_noise_levels(noise)),
            frames=frames,
            seed=seed,
            supersample=supersample,
            passes=passes,
            acquisition=acquisition,
            camera=camera,
            mockup=names[0],
            mockups=tuple(names) if len(names) > 1 else (),
            lighting=light,
            auto_exposure=auto_exposure,
            blank_frames=tuple(int(i) for i in blank.split(",") if i.strip()),
        )
    except ValueError as exc:
        raise _fail(f"bad --distance or --blank: {exc}") from None
    if out_path is not None:
        _output_file(out_path, "--out")
    if results is not None:
        _output_file(results, "--results")
    try:  # one frames part of the campaign runner: the same trials, workers and results
        rows = run_matrix_campaign(
            spec,
            workers=jobs,
            progress=lambda key, s, done, total: console.print(f"[{done}/{total}] {key} {s:.0f} s"),
        )
    except (ValueError, NotImplementedError, ConfigError) as exc:
        raise _fail(str(exc)) from None
    table = markdown_table(summarize(rows)) + "\n" + bias_table(rows)
    if len(names) > 1:
        table += "\n" + mockup_table(rows)
    losses = loss_table(rows)
    if losses:
        table += "\n" + losses
    out.print(table, markup=False, highlight=False, soft_wrap=True)
    if out_path is not None:
        with _writing(out_path, "--out"):
            out_path.write_text(table, encoding="utf-8")
    if results is not None:
        with _writing(results, "--results"), results.open("w", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(asdict(row), allow_nan=True) + "\n")


@app.command("path")
def approach_path(
    system: Annotated[str, typer.Option(help="Estimator: corners | lines | ellipses.")],
    frames: Annotated[int, typer.Option(min=2, help="Frames from the start to 0.5 m.")] = 120,
    noise: NoiseOpt = Noise.low,
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
    auto_exposure: AutoExposureOpt = False,
    supersample: SupersampleOpt = 1,
) -> None:
    """Open loop: one estimator tracks the target along a scripted approach path (2.5 m →
    0.5 m, re-centring an off-centre, rotated start); print errors by distance and by the
    fraction of the ring in view, and count the frames that claim a pose beyond their own 3σ
    without flagging it ambiguous. (The closed loop is `satgrasp approach`.) Rendered one
    sample a pixel unless asked, as the reference study's path; close up its edges' aliasing
    then shows in the panel systems' fits as over-confidence (docs/any_mockup.md)."""
    from configuration.random_mockup import mockup_names
    from hil.evaluation.approach_path import (
        ApproachPath,
        markdown_approach,
        markdown_visible,
        run_approach,
    )

    if out_path is not None:
        _output_file(out_path, "--out")
    try:
        names = mockup_names(mockup)
        path = ApproachPath(start_distance_m=start_distance)
        results = []
        for name in names:
            results += run_approach(
                system,
                frames=frames,
                noise=noise.value,
                camera=camera,
                mockup=name,
                seed=seed,
                path=path,
                lighting=light,
                auto_exposure=auto_exposure,
                supersample=supersample,
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
        with _writing(out_path, "--out"):
            out_path.write_text(text, encoding="utf-8")


@app.command()
def record(
    out_dir: Annotated[Path, typer.Option("--out", help="Directory for the recording.")],
    frames: Annotated[int, typer.Option(min=2, help="Frames from 2.5 m to 0.5 m.")] = 120,
    noise: NoiseOpt = Noise.low,
    camera: CameraOpt = "reference",
    mockup: MockupOpt = "default",
    seed: Annotated[int, typer.Option(help="Noise seed.")] = 0,
    codec: Annotated[
        Codec, typer.Option(help="Video codec: ffv1 (lossless) or mjpg.")
    ] = Codec.ffv1,
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

    _output_dir(out_dir, "--out")
    options = dict(
        frames=frames,
        noise=noise.value,
        camera=camera,
        mockup=mockup,
        seed=seed,
        codec=codec.value,
    )
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


BenchSystemsOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--system", help="Estimator(s); repeat for several [default: corners, lines, ellipses]."
    ),
]
BenchFramesOpt = Annotated[
    int, typer.Option(min=1, help="Frames per cell (system, camera, distance, noise).")
]


def _bench_rows_json(rows: list, full_frame: list | None = None) -> str:
    document: dict[str, Any] = {"rows": [r.to_dict() for r in rows]}
    if full_frame is not None:
        document["full_frame"] = [r.to_dict() for r in full_frame]
    return json.dumps(document, indent=2, allow_nan=False)


@bench_app.command("estimate")
def bench_estimate(
    system: BenchSystemsOpt = None,
    camera: Annotated[
        list[str] | None,
        typer.Option(help="Camera profile(s); repeat for several [default: reference]."),
    ] = None,
    distance: Annotated[
        list[float] | None,
        typer.Option(min=0.1, help="Distance(s) in m; repeat for several [default: 3 2 1.2 0.5]."),
    ] = None,
    noise: Annotated[
        list[Noise] | None,
        typer.Option(help="Image noise; repeat for several [default: low]."),
    ] = None,
    frames: BenchFramesOpt = 10,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the rows as one JSON object on stdout.")
    ] = False,
) -> None:
    """Per system, camera, distance and noise, on the same rendered frames: tracking (prior
    1 cm / 1° off the truth) and acquisition time per frame (median, p95; one thread), and the
    plain OpenCV pipeline given the same prior, with the time and accuracy ratios."""
    from hil.analysis.bench import DISTANCES_M, SYSTEMS, comparison_timings

    try:
        rows = comparison_timings(
            tuple(system or SYSTEMS),
            cameras=tuple(camera or ("reference",)),
            distances_m=tuple(distance or DISTANCES_M),
            noises=tuple(n.value for n in (noise or [Noise.low])),
            frames=frames,
            progress=console,
        )
    except (ConfigError, ValueError, NotImplementedError) as exc:
        raise _fail(str(exc)) from None
    if as_json:
        typer.echo(_bench_rows_json(rows))
        return
    from rich.table import Table

    table = Table(
        title="ms per frame (median, p95; one thread); time ratio satgrasp / OpenCV; "
        "accuracy ratio OpenCV / satgrasp error (position, attitude); frames valid"
    )
    columns = (
        "system", "camera", "m", "noise", "tracking", "p95", "acquisition", "p95", "OpenCV",
        "time ratio", "accuracy ratio", "valid",
    )  # fmt: skip
    for column in columns:
        table.add_column(column, justify="right")
    for r in rows:
        table.add_row(
            r.system, r.camera, f"{r.distance_m:.1f}", r.noise,
            f"{r.tracking_median_ms:.1f}", f"{r.tracking_p95_ms:.1f}",
            f"{r.acquisition_median_ms:.1f}", f"{r.acquisition_p95_ms:.1f}",
            f"{r.opencv_median_ms:.1f}", f"{r.time_ratio:.2f}",
            f"{r.position_accuracy_ratio:.1f}, {r.attitude_accuracy_ratio:.1f}",
            f"{r.tracking_valid}/{r.frames}, {r.acquisition_valid}/{r.frames}, "
            f"{r.opencv_valid}/{r.frames}",
        )  # fmt: skip
    out.print(table)


def _git_revision() -> str | None:
    """The checked-out commit (short hash, ``+`` when the tree has changes), if in a git tree."""
    import subprocess

    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+" if dirty else "")


@bench_app.command("report")
def bench_report(
    out_path: Annotated[Path, typer.Option("--out", help="Markdown file to write.")] = Path(
        "docs/benchmarks.md"
    ),
    frames: BenchFramesOpt = 10,
    seconds: Annotated[
        float,
        typer.Option(min=2.0, help="Seconds each full-frame pipeline (serial, concurrent) runs."),
    ] = 20.0,
    as_json: Annotated[
        bool, typer.Option("--json", help="Also print the rows as one JSON object on stdout.")
    ] = False,
) -> None:
    """The whole benchmark of issue 12 in one run, written as markdown (docs/benchmarks.md):
    every system against the OpenCV pipeline at VGA (reference) and 1280×800 (oak_d_rgb),
    3 / 2 / 1.2 / 0.5 m, noise low and high, then the full frame (three systems + fusion)
    serial and concurrent, with the machine described and what meets the targets."""
    from hil.analysis.bench import comparison_timings, full_frame_timings
    from hil.analysis.bench_report import benchmarks_markdown, describe_machine

    cameras = ("reference", "oak_d_rgb")
    try:
        out_path.parent.mkdir(parents=True, exist_ok=True)
        rows = comparison_timings(
            cameras=cameras, noises=("low", "high"), frames=frames, progress=console
        )
        full_frame = full_frame_timings(cameras, seconds=seconds, progress=console)
    except (ConfigError, ValueError, NotImplementedError, OSError) as exc:
        raise _fail(str(exc)) from None
    command = f"satgrasp bench report --out {out_path} --frames {frames} --seconds {seconds:g}"
    text = benchmarks_markdown(
        rows, full_frame, describe_machine(), command=command, frames=frames,
        revision=_git_revision(),
    )  # fmt: skip
    try:
        out_path.write_text(text + "\n", encoding="utf-8")
    except OSError as exc:
        raise _fail(f"cannot write {out_path}: {exc}") from None
    if as_json:
        typer.echo(_bench_rows_json(rows, full_frame))
        console.print(f"wrote {out_path}")
    else:
        out.print(f"wrote {out_path}", markup=False, highlight=False)


@app.command()
def report(
    log: Annotated[
        Path,
        typer.Argument(
            help="Trial log (.mcap), complete or cut off by a crash; or a campaign directory."
        ),
    ],
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
    """Plots and an HTML page for one trial log (or, for a campaign directory, its tables in
    the reference study's layout beside the reference's numbers, figures and a page): range and phases, errors of each estimator
    and of the fused estimate against ground truth (simulation), estimator results accepted /
    rejected / lost / stale, commands, control-loop timing and vision latency, and a summary.
    With --json, the same figures as one JSON object (docs/trial_logs.md lists the keys)."""
    if log.is_dir():  # a campaign: its tables beside the reference's, figures, a page
        from hil.cli_campaigns import campaign_report

        return campaign_report(log, out_dir)
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

    from hil.analysis.bench_loop import control_tick_timing, pipeline_timing, tracking_frames

    try:
        tick = control_tick_timing(config, ticks=ticks)
    except (ValueError, ConfigError) as exc:
        raise _fail(str(exc)) from None
    out.print(
        f"control tick without vision ({tick.ticks} ticks, period {tick.period_ms:.1f} ms): "
        f"p50 {tick.p50_ms:.2f} ms, p99 {tick.p99_ms:.2f} ms, max {tick.max_ms:.2f} ms"
    )
    systems = ("corners", "lines", "ellipses")
    console.print("rendering a stretch of the approach (2.0 → 1.5 m at 0.25 m/s, 30 fps) …")
    frames = tracking_frames(camera, "default")
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
    noise: Any,
    systems: str | None,
    links: Any,
    clock: Any = None,
    settings: list[str] | None = None,
):
    from configuration.simulation import load_simulation, with_overrides, with_settings

    try:
        sim = with_settings(load_simulation(config), settings or [])
        return with_overrides(
            sim,
            noise={"preset": noise.value} if noise is not None else None,
            systems=systems.split(",") if systems else None,
            links=None if links is None else links.value,
            clock=None if clock is None else clock.value,
        )
    except ValueError as exc:  # ConfigError or a validation error of an override
        raise _fail(str(exc)) from None


@app.command()
def approach(
    config: SimOpt = "sim",
    noise: Annotated[Noise | None, typer.Option(help="Override the image noise.")] = None,
    seed: Annotated[int, typer.Option(help="Seed of the random start and the image noise.")] = 1,
    systems: Annotated[
        str | None, typer.Option(help="Comma-separated estimators, e.g. corners,lines,ellipses.")
    ] = None,
    links: Annotated[
        Links | None,
        typer.Option(help="Track and gripper reached directly, or over pymodbus (tcp)."),
    ] = None,
    clock: Annotated[
        Clock | None,
        typer.Option(
            help="sim: stepped as fast as possible with vision time charged (deterministic); "
            "wall: the simulated world runs in real time in its own processes, like a rig. "
            "[default: the config's, sim]"
        ),
    ] = None,
    settings: SetOpt = None,
    light: Annotated[
        str | None,
        typer.Option(
            "--light",
            help="Light: default | harsh (a low side sun with shadows) | random (a random "
            "mock-up's own, else the seed's). [default: the config's]",
        ),
    ] = None,
    log_dir: Annotated[Path, typer.Option(help="Directory for the trial log.")] = Path("runs"),
    report_too: Annotated[
        bool, typer.Option("--report/--no-report", help="Write the report after the trial.")
    ] = True,
) -> None:
    """Run one approach (2.5 m → 0.5 m stand-off, grasp, retreat) with a live progress line;
    write its trial log (MCAP) and, by default, its report. Simulated by default; the config's
    devices: section may name the real drivers against emulators (emulated) or the rig.

    Ctrl-C (SIGINT) or SIGTERM stops the arm and the track within one control period, ends
    the trial with that reason, closes the log and writes the report. Exit status: 0 success;
    1 the approach failed or was aborted; 2 bad input; 3 the trial was ended by an error (a
    device, the software, a log that cannot be written; the arm and the track are stopped and
    the reason is printed and logged); 130 / 143 interrupted by SIGINT / SIGTERM."""
    import time

    from configuration.simulation import with_light
    from hil.runtime.signals import Interrupted, StopSignals

    sim = _simulation(config, noise, systems, links, clock, settings)
    if light is not None:
        try:
            sim = with_light(sim, light, seed)
        except ValueError as exc:
            raise _fail(f"--light: {exc}") from None
    _output_dir(log_dir, "--log-dir")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    log_path = log_dir / f"approach_{sim.noise.preset}_seed{seed}_{stamp}.mcap"
    render = sim.render.for_noise(sim.noise)
    out.print(
        f"{sim.devices.kind} approach: systems {', '.join(sim.systems)}, noise {sim.noise.preset}, "
        f"supersample {render.supersample} in {render.passes} pass(es), seed {seed}, "
        f"clock {sim.clock}"
    )
    with StopSignals() as signals:
        try:
            code = _approach(sim, seed, log_path, signals)
            if report_too and log_path.exists():
                code = _approach_report(log_path, code)
        except Interrupted as exc:  # during start-up: the loop had not begun, nothing moved
            logged = f"log {log_path}" if log_path.exists() else "no log written"
            out.print(f"{exc} during start-up; nothing moved; {logged}")
            code = exc.exit_code
    raise typer.Exit(code=code)


def _approach(sim: Any, seed: int, log_path: Path, signals: Any) -> int:
    """Run the trial with a live progress line, print how it ended; the exit status."""
    from rich.live import Live

    from hil.progress import tick_line
    from hil.runtime.compose import Trial
    from hil.runtime.loop import describe_exception

    last_shown = [-1.0]
    result = error = None
    with Live("", console=console, refresh_per_second=8, transient=False) as live:

        def on_tick(record) -> None:
            if record.t - last_shown[0] >= 0.25 or record.phase in ("done", "abort"):
                last_shown[0] = record.t
                live.update(tick_line(record))

        running = False
        try:
            trial = Trial(sim, seed=seed, log_path=log_path, on_tick=on_tick, signals=signals)
            with trial:
                running = True
                result = trial.run()
        except Exception as exc:
            if not running:  # a configuration, a log path, a process that would not start
                user = isinstance(exc, ValueError | NotImplementedError)
                message = str(exc) if user else describe_exception(exc)
                raise _fail(message, 2 if user else 3) from None
            error = exc
    console.print()  # end the live line
    loop = trial.loop
    log_error = trial.log.error
    logged = f"log {log_path}" + (" (incomplete)" if log_error else "")
    if error is not None:
        ending = loop.ending or f"trial ended by {describe_exception(error)}; arm and track stopped"
        out.print(f"[bold red]ERROR[/]: {escape(ending)}; {escape(logged)}")
        code = 3
    elif signals.received is not None and loop.ending and loop.ending.startswith("interrupted"):
        out.print(f"{escape(loop.ending)}; {escape(logged)}")
        code = signals.exit_code
    else:
        code = _print_outcome(result, sim, log_path)
        if signals.received is not None:  # after the loop had ended by itself
            code = signals.exit_code
    if log_error:
        out.print(
            f"[bold red]trial log incomplete[/]: writing failed at t = {trial.log.error_t:.2f} s "
            f"({escape(log_error)}); the log holds what was flushed before"
        )
        code = 3 if code < 128 else code  # a signal's status stands
    return code


def _print_outcome(result: Any, sim: Any, log_path: Path) -> int:
    o = result.outcome
    verdict = "[bold green]SUCCESS[/]" if result.success else "[bold red]FAILURE[/]"
    kind = "simulated" if result.clock == "sim" else "on the wall clock"
    out.print(
        f"{verdict}: ended in {o.phase} after {o.duration_s:.1f} s {kind} ({o.ticks} ticks, "
        f"{o.deadline_misses} deadline misses)"
    )
    if o.abort_reason:
        out.print(f"abort reason: {escape(o.abort_reason)}")
    if result.standoff_error_m is not None:
        import math

        out.print(
            f"true camera error at the stand-off: {1000 * result.standoff_error_m:.2f} mm, "
            f"{math.degrees(result.standoff_error_rad):.3f}° (success needs ≤ "
            f"{1000 * sim.approach.standoff.success_position_m:.0f} mm and "
            f"{sim.approach.standoff.success_angle_deg}°)"
        )
    out.print(f"trial log: {log_path}")
    return 0 if result.success else 1


def _approach_report(log_path: Path, code: int) -> int:
    """Write the trial's report beside its log; a report that cannot be written is one line
    (the trial's exit status stands), a second signal skips it."""
    from hil.analysis.report import make_report
    from hil.logs.triallog import TrialLogError
    from hil.runtime.signals import Interrupted

    target = log_path.with_name(log_path.stem + "_report")
    try:
        index = make_report(log_path, target)
    except (OSError, TrialLogError) as exc:
        console.print(f"[yellow]report not written[/] to {target}: {escape(str(exc))}")
        return code
    except Interrupted as exc:
        console.print(f"report not written: {exc}")
        return exc.exit_code
    out.print(f"report: {index}")
    return code


@app.command()
def campaign(
    file: Annotated[
        Path | None,
        typer.Argument(
            help="Campaign file (YAML) or a built-in name (smoke, reference). Without it: "
            "closed-loop approaches from --seeds, --noise, --config."
        ),
    ] = None,
    out_dir_option: Annotated[
        Path | None,
        typer.Option("--out", help="Campaign directory [default: runs/campaigns/<name>]."),
    ] = None,
    workers: Annotated[int, typer.Option(min=1, help="Trials run at once.")] = 1,
    executor: Annotated[
        str, typer.Option(help="local (processes) | dask (needs satgrasp[cluster]).")
    ] = "local",
    scheduler: Annotated[
        str | None,
        typer.Option(help="Dask scheduler address [default: a LocalCluster on 127.0.0.1]."),
    ] = None,
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
    jobs: Annotated[int, typer.Option(min=1, help="Same as --workers (older name).")] = 1,
    settings: SetOpt = None,
    out_dir: Annotated[Path, typer.Option(help="Same as --out (older name).")] = Path(
        "runs/campaign"
    ),
) -> None:
    """Run a campaign: every trial of FILE (open-loop frames, open-loop path, closed-loop
    approaches; axes swept, seeds per cell) that has no result yet — so a killed campaign
    resumes — on local processes or a Dask cluster; OUT/summary.csv and summary.parquet hold
    one row per cell. Without FILE: closed-loop approaches (random starts as in the reference:
    2.5 m, ±0.3 m off centre, ±10° rotated), summarised per trial in OUT/summary.md too."""
    from hil.cli_campaigns import load_campaign_file, run_with_progress

    workers = max(workers, jobs)
    if file is not None:
        campaign_config, source = load_campaign_file(file)
        run = run_with_progress(
            campaign_config, out_dir_option, workers, executor, scheduler, source
        )
        out_print = f"report: satgrasp report {run.summary_csv.parent}"
        console.print(out_print, markup=False, highlight=False)
        return
    from hil.analysis.campaign import campaign_markdown, seeds_campaign, summarize_log
    from hil.analysis.campaigns.spec import expand
    from hil.analysis.campaigns.trials import log_path

    levels = _noise_levels(noise)
    sim = _simulation(config, None, systems, None, None, settings)
    target = out_dir_option if out_dir_option is not None else out_dir
    _output_dir(target, "--out")
    campaign_config = seeds_campaign(sim, range(first_seed, first_seed + seeds), levels)
    run_with_progress(campaign_config, target, workers, executor, scheduler)
    rows = [
        summarize_log(log_path(target, t), t.seed, t.cell["noise"]) for t in expand(campaign_config)
    ]
    table = campaign_markdown(rows)
    with _writing(target / "summary.md", "--out"):
        (target / "summary.md").write_text(table, encoding="utf-8")
    out.print(table, markup=False, highlight=False)
    out.print(f"summary: {target / 'summary.md'}")


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

    if out_path is not None:
        _output_file(out_path, "--out")
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
        with _writing(out_path, "--out"):
            out_path.write_text(text, encoding="utf-8")


@app.command()
def demo(
    out_dir: Annotated[
        Path, typer.Option(help="Directory for the trial log and its report.")
    ] = Path("runs"),
) -> None:
    """The simulated demo on the embedded default configuration (configs/sim.yaml): one full
    approach with low noise — 2.5 m start, stand-off, grasp, retreat — its trial log and report."""
    _output_dir(out_dir, "--out-dir")
    approach(
        config="sim",
        noise=Noise.low,
        seed=1,
        systems=None,
        links=None,
        clock=None,
        settings=None,
        log_dir=out_dir,
        report_too=True,
    )


def main() -> None:
    keep_freed_memory()  # the estimators' per-frame images on pages already mapped
    try:
        app()
    except ConfigError as exc:  # a configuration named deeper than a command's own checks
        console.print(f"[bold red]error:[/] {escape(str(exc))}")
        sys.exit(2)
    except OSError as exc:  # a file met deeper than a command's own checks: still one line
        where = f"{exc.filename}: " if exc.filename else ""
        console.print(f"[bold red]error:[/] {escape(where + (exc.strerror or str(exc)))}")
        sys.exit(2)
