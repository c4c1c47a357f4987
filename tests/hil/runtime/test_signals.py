"""SIGINT / SIGTERM handlers: a flag while a loop runs, ``Interrupted`` otherwise, the previous
handlers back afterwards (in-process: ``signal.raise_signal`` runs the handler at once)."""

import signal

import pytest

from hil.runtime.signals import Interrupted, StopSignals


def test_stop_signals_raise_interrupted_when_no_loop_runs():
    with StopSignals() as signals, pytest.raises(Interrupted) as raised:
        signal.raise_signal(signal.SIGTERM)
    assert raised.value.name == "SIGTERM" and raised.value.exit_code == 143
    assert str(raised.value) == "interrupted by SIGTERM"
    assert signals.received == signal.SIGTERM and signals.exit_code == 143


def test_stop_signals_route_to_the_loop_only_set_its_flag():
    requests = []
    with StopSignals() as signals:
        signals.route_to = requests.append
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGTERM)
    assert requests == ["interrupted by SIGINT", "interrupted by SIGTERM"]
    assert signals.received == signal.SIGINT and signals.exit_code == 130  # the first counts


def test_stop_signals_put_the_previous_handlers_back():
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with StopSignals() as signals:
        assert signal.getsignal(signal.SIGINT) == signals._handle
    assert {s: signal.getsignal(s) for s in before} == before
    assert signals.exit_code is None
