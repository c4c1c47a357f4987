"""``satgrasp check-rig --config FILE``: one line per device, and an exit code that says whether
the rig is ready (0 ready, 1 not ready, 2 a bad configuration). See hil/runtime/rig_check.py
and docs/rig_setup.md."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.console import Console

console = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True, highlight=False)


def check_rig(
    config: Annotated[
        str,
        typer.Option(
            help="Trial configuration whose devices to check: a built-in name (emulated, real) "
            "or a YAML path."
        ),
    ],
    timeout_s: Annotated[
        float,
        typer.Option(min=0.5, max=120.0, help="Each device's check is stopped after this long."),
    ] = 10.0,
) -> None:
    """Connect to every device of the configuration — read the arm's pose and safety state,
    grab a camera frame and report its intrinsics, read the gripper's and the track's status —
    and print one line per device. Read-only: nothing is activated, nothing moves. An emulated
    configuration starts its emulators first. Exit code 0 when every device is ready."""
    from configuration.simulation import load_simulation
    from hil.runtime.rig_check import check_rig as run_checks

    try:
        sim = load_simulation(config)
    except ValueError as exc:  # ConfigError: file, field and line
        console.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=2) from None
    out.print(f"checking the {sim.devices.kind} rig of {config} (read-only)")
    checks = run_checks(sim, timeout_s=timeout_s)
    for check in checks:
        out.print(check.line(), markup=False)
    ready = all(check.ready for check in checks)
    out.print("rig ready" if ready else "rig NOT ready", markup=False)
    raise typer.Exit(code=0 if ready else 1)
