"""Commands around campaigns and logs: the campaign runner (``satgrasp campaign FILE``), the
Cramér–Rao bound (``crb``), log recovery (``recover``). Thin: they parse options, call the
library and print; bad input exits with status 2 and one line."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

console = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


def fail(message: str) -> typer.Exit:
    console.print(f"[bold red]error:[/] {message}", markup=True, highlight=False)
    return typer.Exit(code=2)


def load_campaign_file(file: Path):
    """(config, its text) of a campaign file or built-in name; one line on a bad file."""
    from configuration.campaign import load_campaign_config
    from configuration.files import resolve_config_path

    try:
        path = resolve_config_path(file, "campaigns")
        return load_campaign_config(path), path.read_text(encoding="utf-8")
    except ValueError as exc:  # ConfigError
        raise fail(str(exc)) from None


def run_with_progress(
    config,
    out_dir: Path | None,
    workers: int,
    executor: str,
    scheduler: str | None,
    source: str | None = None,
):
    """Run (or resume) a campaign with a progress bar and ETA; returns the ``CampaignRun``."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from hil.analysis.campaigns.runner import run_campaign
    from hil.analysis.campaigns.spec import expand
    from hil.progress import campaign_line

    if executor not in ("local", "dask"):
        raise fail(f"--executor must be local or dask; got {executor!r}")
    if scheduler is not None and executor != "dask":
        raise fail("--scheduler needs --executor dask")
    try:
        trials = expand(config)
    except ValueError as exc:  # CampaignError
        raise fail(str(exc)) from None
    target = out_dir if out_dir is not None else Path("runs") / "campaigns" / config.name
    bar = Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[last]}"),
        console=console,
    )
    out.print(
        f"campaign {config.name}: {len(trials)} trials, executor {executor}, workers {workers}, "
        f"results in {target}"
    )
    with bar:
        task = bar.add_task(config.name, total=None, last="")

        started = time.monotonic()

        def progress(key: str, seconds: float, done: int, total: int) -> None:
            bar.update(task, total=total, completed=done, last=f"{key} {seconds:.0f} s")
            if not console.is_terminal:  # a log file sees no bar: a line per trial instead
                elapsed = time.monotonic() - started
                console.print(
                    campaign_line(key, seconds, done, total, elapsed),
                    markup=False,
                    highlight=False,
                )

        try:
            run = run_campaign(
                config,
                target,
                workers=workers,
                executor=executor,
                scheduler=scheduler,
                progress=progress,
                source=source,
            )
        except ValueError as exc:
            raise fail(str(exc)) from None
        except Exception as exc:  # a trial that crashed: the finished ones are kept
            raise fail(
                f"a trial failed ({type(exc).__name__}: {exc}); the finished trials are kept in "
                f"{target}, run the campaign again to resume"
            ) from None
    out.print(
        f"{run.ran} trials run, {run.skipped} already done, {run.wall_s:.0f} s; "
        f"summary: {run.summary_csv}" + (f", {run.summary_parquet}" if run.summary_parquet else "")
    )
    return run


def crb(
    mockup: Annotated[str, typer.Option(help="Mock-up: 'default' or a YAML path.")] = "default",
    camera: Annotated[
        str, typer.Option(help="Camera profile: a built-in name or a YAML path.")
    ] = "reference",
    noise: Annotated[str, typer.Option(help="Noise preset: low | high.")] = "low",
    distance: Annotated[
        str, typer.Option(help="Comma-separated distances (m) in front of the ring face.")
    ] = "3,2,1.2",
) -> None:
    """The Cramér–Rao bound of the pose from one frame for each system's features and for all
    of them together: 1σ of tilt, depth and lateral position, and the mean errors an efficient
    estimator would show (the floor a campaign's efficiency columns divide by)."""
    from configuration.files import ConfigError
    from hil.evaluation.crb import bound_table

    try:
        distances = tuple(float(d) for d in distance.split(","))
    except ValueError:
        raise fail(f"--distance: expected comma-separated metres; got {distance!r}") from None
    if any(d <= 0 for d in distances):
        raise fail(f"--distance must be positive; got {distance}")
    if noise not in ("low", "high"):
        raise fail(f"--noise must be low or high (a bound needs Gaussian noise); got {noise!r}")
    try:
        text = bound_table(noise, distances, camera=camera, mockup=mockup)
    except (ConfigError, ValueError) as exc:
        raise fail(str(exc)) from None
    out.print(text, markup=False, highlight=False)


def recover(
    log: Annotated[Path, typer.Argument(help="Trial log (.mcap) whose writer was killed.")],
    out_path: Annotated[
        Path | None,
        typer.Option("--out", help="Where to write [default: <log>_recovered.mcap beside it]."),
    ] = None,
) -> None:
    """Rewrite a killed trial's log (no MCAP footer, its last chunk cut) into a complete,
    indexed MCAP file that any MCAP reader opens to the end."""
    from hil.logs.triallog import TrialLogError
    from hil.logs.triallog import recover as recover_log

    target = out_path if out_path is not None else log.with_name(f"{log.stem}_recovered.mcap")
    if target.exists():
        raise fail(f"{target} exists; choose another --out")
    try:
        recover_log(log, target)
    except (FileNotFoundError, TrialLogError, ValueError) as exc:
        raise fail(str(exc)) from None
    except OSError as exc:
        raise fail(f"cannot write {target}: {exc}") from None
    out.print(f"recovered: {target}")


def campaign_report(campaign_dir: Path, out_dir: Path | None) -> None:
    """``satgrasp report CAMPAIGN_DIR``: tables beside the reference's, figures, HTML page."""
    from hil.analysis.campaigns.report import CampaignReportError, write_campaign_report

    try:
        index, markdown = write_campaign_report(campaign_dir, out_dir)
    except CampaignReportError as exc:
        raise fail(str(exc)) from None
    except OSError as exc:
        raise fail(f"cannot write the report: {exc}") from None
    out.print(f"report: {index}\ntables: {markdown}")


def compare(
    a: Annotated[Path, typer.Argument(help="Trial log (.mcap) or campaign directory: before.")],
    b: Annotated[Path, typer.Argument(help="The same kind: after.")],
    out_dir: Annotated[
        Path | None, typer.Option("--out", help="Directory for the table and the plot.")
    ] = None,
) -> None:
    """Compare two trials or two campaigns: aligned differences (B − A, B ÷ A) with a
    Mann–Whitney p-value where it applies, and overlaid plots (B against A per cell for
    campaigns, errors against time for trials)."""
    from hil.analysis.campaigns import compare as cmp
    from hil.logs.triallog import TrialLogError

    if a.is_dir() != b.is_dir():
        raise fail("compare two trial logs or two campaign directories, not one of each")
    for path in (a, b):
        if not path.exists():
            raise fail(f"{path} does not exist")
    target = out_dir if out_dir is not None else Path(f"compare_{a.stem}_{b.stem}")
    try:
        if a.is_dir():
            differences = cmp.compare_campaigns(a, b)
            target.mkdir(parents=True, exist_ok=True)
            plot = cmp.plot_campaigns(differences, target / "compare.png")
        else:
            differences, errors_a, errors_b = cmp.compare_trials(a, b)
            target.mkdir(parents=True, exist_ok=True)
            plot = cmp.plot_trials(errors_a, errors_b, target / "compare.png", a.stem, b.stem)
    except (ValueError, TrialLogError, FileNotFoundError) as exc:
        raise fail(str(exc)) from None
    text = cmp.markdown(differences, str(a), str(b))
    (target / "compare.md").write_text(text, encoding="utf-8")
    out.print(text, markup=False, highlight=False)
    out.print(f"table: {target / 'compare.md'}; plot: {plot}")


def video(
    log: Annotated[Path, typer.Argument(help="Trial log (.mcap) with logged frames.")],
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Video file [default: <log>_overlay.mp4].")
    ] = None,
    codec: Annotated[
        str, typer.Option(help="FourCC: vp09 (.mp4, plays in browsers), mp4v, MJPG (.avi).")
    ] = "vp09",
    fps: Annotated[
        float | None, typer.Option(min=0.1, help="Frame rate [default: the logged rate].")
    ] = None,
) -> None:
    """Render the logged frames with each system's features and reprojected model and the
    fused pose (white model, axes) as a video."""
    from hil.analysis.video import VideoError, default_video_path, render_video
    from hil.logs.triallog import TrialLogError

    target = out_path if out_path is not None else default_video_path(log)
    try:
        path, frames = render_video(log, target, codec=codec, fps=fps)
    except (VideoError, TrialLogError, FileNotFoundError) as exc:
        raise fail(str(exc)) from None
    out.print(f"video: {path} ({frames} frames)")
