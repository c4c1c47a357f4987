"""``satgrasp emulate``: loopback emulators of the real devices, in the foreground.

``satgrasp emulate ur --host 127.0.0.2`` serves a UR controller (dashboard 29999, script 30003,
RTDE 30004) that any ur-rtde program can drive, until Ctrl-C.
"""

from __future__ import annotations

from typing import Annotated

import typer
from pydantic import ValidationError
from rich.console import Console

emulate_app = typer.Typer(
    help="Loopback emulators of the real devices' protocols (foreground, until Ctrl-C).",
    no_args_is_help=True,
)
console = Console(stderr=True, soft_wrap=True)
out = Console(soft_wrap=True)


def _fail(message: str) -> typer.Exit:
    console.print(f"[bold red]error:[/] {message}")
    return typer.Exit(code=2)


@emulate_app.command("ur")
def emulate_ur(
    host: Annotated[
        str,
        typer.Option(help="Loopback address to listen on (127.x.y.z); ports 29999, 30003, 30004."),
    ],
    model: Annotated[
        str | None, typer.Option(help="Arm model (ur3e, ur5e, ur10e, ur16e); default: the rig's.")
    ] = None,
    config: Annotated[
        str, typer.Option(help="Rig whose arm is emulated: a built-in name (rig) or a YAML path.")
    ] = "rig",
    unlock_delay_s: Annotated[
        float,
        typer.Option(help="Seconds after a protective stop before it can be unlocked (UR: 5)."),
    ] = 5.0,
) -> None:
    """A UR e-Series controller emulator that the real ur-rtde client drives (see
    docs/ur_emulator.md). Runs in the foreground until interrupted."""
    from sim_backends.loopback import check_loopback
    from sim_backends.ur_emulator import arm_config
    from sim_backends.ur_emulator.server import PORTS, EmulatorServer, EmulatorSettings

    try:
        check_loopback(host, ipv4_only=True)
    except ValueError as exc:
        raise _fail(f"--host: {exc}") from None
    if unlock_delay_s < 0:
        raise _fail(f"--unlock-delay-s must be ≥ 0; got {unlock_delay_s}")
    try:
        arm = arm_config(config, model)
    except ValidationError as exc:
        raise _fail(f"--model: {exc.errors()[0]['msg']}; got {model!r}") from None
    server = EmulatorServer(EmulatorSettings(host=host, arm=arm, unlock_delay_s=unlock_delay_s))
    try:
        server.listen()
    except OSError as exc:
        server.close()
        raise _fail(str(exc.strerror or exc)) from None
    ports = ", ".join(f"{kind} {port}" for kind, port in PORTS.items())
    out.print(
        f"UR emulator ({arm.model}) listening on {host}: {ports}. Ctrl-C stops it.", highlight=False
    )
    server.serve_forever()
    out.print("UR emulator stopped.", highlight=False)
