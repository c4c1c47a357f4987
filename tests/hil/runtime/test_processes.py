"""Stopping the trial's child processes on every way out, started or not."""

import multiprocessing as mp

from hil.runtime.processes import stop_process


def _exit_at_once() -> None:
    return None


def test_stopping_a_process_that_never_started_is_a_no_op() -> None:
    # A process whose start() raised is still in the trial's list; its clean-up must not
    # raise over the error that stopped it (join() asserts on an unstarted process).
    process = mp.get_context("spawn").Process(target=_exit_at_once)
    stop_process(process, timeout_s=0.0)
    assert process.pid is None


def test_stopping_a_started_process_waits_for_it_to_end() -> None:
    process = mp.get_context("spawn").Process(target=_exit_at_once)
    process.start()
    stop_process(process, timeout_s=10.0)
    assert process.exitcode == 0
