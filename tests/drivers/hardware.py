"""Where the real devices are, for the tests marked ``hardware`` (docs/rig_setup.md): each skips
unless its environment variable names the device."""

from __future__ import annotations

import os

import pytest


def modbus_address(variable: str, device_id: int) -> tuple[str, int, int] | None:
    """``host[:port[:device_id]]`` from the environment variable ``variable`` (port 502 and
    ``device_id`` by default), or None when it is not set."""
    text = os.environ.get(variable, "").strip()
    if not text:
        return None
    host, _, rest = text.partition(":")
    port, _, unit = rest.partition(":")
    try:
        return host, int(port or 502), int(unit or device_id)
    except ValueError:
        raise pytest.UsageError(f"{variable}={text!r}: expected host[:port[:device_id]]") from None


def needs(variable: str, what: str) -> pytest.MarkDecorator:
    """Skip unless ``variable`` is set (``what``: the device, for the reason)."""
    return pytest.mark.skipif(
        not os.environ.get(variable), reason=f"set {variable} to the {what} (host[:port[:id]])"
    )
