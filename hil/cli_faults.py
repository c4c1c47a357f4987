"""``satgrasp faults``: the fault-injection suite (``hil.analysis.faults``) with its table.

One short simulated trial per fault kind; the table says when each fault was injected, when the
loop could first see it, when it stopped, in how many control periods, how the trial ended,
whether the log opens and what reason it names. Exit status 0 when every row passed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

console = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


def faults_command(
    config: Annotated[
        str, typer.Option("--config", help="Simulation: 'sim' (configs/sim.yaml) or a YAML path.")
    ] = "sim",
    only: Annotated[
        list[str] | None,
        typer.Option("--only", help="Run only this fault kind (repeatable). Default: all."),
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of every fault trial's start.")] = 2,
    out_dir: Annotated[Path, typer.Option(help="Directory for the trials' logs.")] = Path(
        "runs/faults"
    ),
) -> None:
    """Inject each fault into a short simulated approach and tabulate the reaction."""
    from configuration.files import ConfigError
    from configuration.simulation import FAULT_KINDS, load_simulation
    from hil.analysis.faults import run_suite, table

    kinds = list(only or FAULT_KINDS)
    unknown = [k for k in kinds if k not in FAULT_KINDS]
    if unknown:
        console.print(
            f"[bold red]error:[/] --only: unknown fault {unknown[0]!r}; one of "
            f"{', '.join(FAULT_KINDS)}"
        )
        raise typer.Exit(code=2)
    try:
        base = load_simulation(config)
    except (ConfigError, ValueError) as exc:
        console.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from None

    def progress(row) -> None:
        verdict = "[green]pass[/]" if row.passed else "[bold red]FAIL[/]"
        console.print(f"{row.kind}: {verdict} — {row.final}; log {row.log_path}")

    rows = run_suite(base, kinds, seed=seed, out_dir=out_dir, progress=progress)
    out.print(table(rows, 1.0 / base.approach.servo.control_rate_hz), markup=False)
    raise typer.Exit(code=0 if all(r.passed for r in rows) else 1)
