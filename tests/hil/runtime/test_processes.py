"""The trial's child processes: stopping them on every way out, started or not, and how their
allocator keeps memory."""

import multiprocessing as mp
import subprocess
import sys

from hil.runtime.processes import stop_process

#: A process that builds and frees a VGA frame's three float images 50 times and prints its page
#: faults, after ``keep_freed_memory`` when its argument says so.
_FRAMES_SCRIPT = """
import resource, sys
import numpy as np
from hil.runtime.processes import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def frame():
    image = np.ones((480, 640), np.float32)
    twice = image * 2.0
    return float((twice + image)[0, 0])
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(50):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _page_faults(mode: str) -> int:
    done = subprocess.run(
        [sys.executable, "-c", _FRAMES_SCRIPT, mode], capture_output=True, text=True, check=True
    )
    return int(done.stdout)


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


def test_kept_freed_memory_serves_each_frames_images_without_page_faults() -> None:
    # glibc's default maps each image afresh and hands it back when freed: every frame's
    # images fault in page by page (a tenth of a vision worker's time).
    assert _page_faults("default") > 5000
    assert _page_faults("keep") < 100
