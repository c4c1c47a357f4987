"""The vision pipeline beside the control loop: newest frames in, fused estimates out.

Data flow of one frame (docs/architecture.md):

1. ``on_frame``: the camera hands over its newest frame (capture stamp = mid-exposure). A frame
   that is replaced before any estimator took it is dropped and counted. A frame whose stamp
   does not advance, or whose image repeats the previous one byte for byte while the camera
   moved (a CRC-32 fingerprint of the pixels), is a camera fault that stops the trial.
2. ``step``: every system whose worker is free takes the newest frame it has not processed yet,
   with fusion's prior *at the frame's capture stamp* and the camera-to-carriage pose of that
   instant — so the three systems run concurrently, each as fast as it can, on the newest data.
   With fewer ``slots`` than systems (fewer cores than estimators) they take turns: the system
   that started longest ago goes first, and each result comes as soon as one core allows; a
   system still busy on a frame already too old to act on no longer holds its slot.
   While fusion has no track yet, a system's own latest pose (in the carriage frame, so the
   arm's and the track's motion since are accounted for) seeds its next search: a search
   without a prior can take longer than ``max_frame_age_s``, and its result, too old to act on,
   still tells the next search where to look.
3. When a result comes back, fusion applies it at the frame's capture stamp with ``X_CM`` of that
   instant (``PoseFusion`` re-filters when results arrive out of capture order) — unless the
   frame is older than ``max_frame_age_s`` by then: a stale result is discarded, never acted on.
4. ``latest``: the filter's newest state (``FusionState``) and the pipeline's counters; the control
   loop predicts that state to its own tick time. It never waits for any of this.

The same object runs in both clocks. Under ``--clock sim`` it is stepped between control ticks
with ``InlineWorkers`` that charge each system a modelled processing time (deterministic); under
``--clock wall`` it runs in a process of its own with ``ProcessWorkers`` (``hil.runtime.wall``).
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from configuration.vision import VisionConfig
from estimators.frame import Frame, frame_problem
from estimators.fusion import FusionState, PoseFusion
from estimators.geometry import Pose
from estimators.measurement import Measurement, decided_parts, honest
from hil.logs.records import VisionOutcome, VisionRecord
from hil.logs.triallog import encode_image
from hil.runtime.history import StateHistory, StateSample
from hil.runtime.workers import VisionJob, VisionResult, Workers

#: How long a system's own pose may seed its next search (s): the mock-up sits still on its
#: carriage, so its pose there holds for a while; a wrong seed only costs a search.
SEED_MAX_AGE_S = 2.0


@dataclass(frozen=True, slots=True, eq=False)
class VisionStatus:
    """What the control loop takes from the vision side at a tick.

    ``fusion``: the filter's newest state (None before the first measurement); the loop predicts
    it to its own time with ``estimators.fusion.estimate_from_state``. ``newest_frame_stamp``:
    capture stamp of the newest usable frame received; ``frame_problem``: why the newest frame
    was unusable, if it was. ``estimator_faults`` counts estimator malfunctions (an exception,
    non-finite output) and ``estimator_fault`` names the latest: the supervisor stops on a new one.
    ``camera_fault``: the camera delivers frames that cannot be live (a stamp that does not
    advance, the same image while the camera moves); it latches, and the loop aborts on it.
    """

    fusion: FusionState | None
    frames_received: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    results_stale: int = 0
    newest_frame_stamp: float | None = None
    frame_problem: str | None = None
    estimator_faults: int = 0
    estimator_fault: str | None = None
    camera_fault: str | None = None


def image_fingerprint(image: np.ndarray) -> int:
    """CRC-32 of the pixels (≈ 0.5 ms for 640×480×3): equal for a repeated image."""
    return zlib.crc32(memoryview(np.ascontiguousarray(image)).cast("B"))


@dataclass(frozen=True, slots=True, eq=False)
class LoggedImage:
    """A frame the trial log keeps (one every ``log_frames_every_s``), already JPEG-encoded:
    encoding a VGA frame takes milliseconds, which belong on the vision side, not in a tick."""

    stamp: float
    jpeg: bytes


class VisionPipeline:
    """Frames → estimators (each on the newest frame it can take) → fusion at capture time.

    ``t0`` is the trial's start on the same clock as the stamps: records carry times since it.
    """

    def __init__(
        self,
        *,
        systems: Sequence[str],
        fusion: PoseFusion,
        history: StateHistory,
        workers: Workers,
        config: VisionConfig,
        t0: float = 0.0,
        slots: int | None = None,
    ):
        self.systems = tuple(systems)
        #: How many systems may process a frame at once (``VisionConfig.estimator_slots``).
        self.slots = len(self.systems) if slots is None else slots
        self.fusion = fusion
        self.history = history
        self.workers = workers
        self.config = config
        self.t0 = t0
        self._newest: Frame | None = None
        self._newest_taken = False
        self._last_seq: dict[str, int] = {s: -1 for s in self.systems}
        self._last_start: dict[str, float] = {s: -math.inf for s in self.systems}
        #: The job each busy system is on.
        self._running: dict[str, VisionJob] = {}
        #: Per (system, acquiring): the time (s) its last frame took (faded by ``_fade``).
        self._took: dict[tuple[str, bool], float] = {}
        #: Per (system, acquiring): how much its time varies from one frame to the next (a
        #: running mean of the absolute change, s).
        self._jitter: dict[tuple[str, bool], float] = {}
        #: Per system: (capture stamp, X_MT, what it decided — ``decided_parts``) of its latest
        #: valid pose, to seed its next search.
        self._seeds: dict[str, tuple[float, Pose, tuple[bool, bool]]] = {}
        #: Per busy system given a prior: what that prior had decided — (roll, circle) as in
        #: ``decided_parts`` — so that an answer that kept the prior's choice is reported as
        #: honestly as the ``Tracker`` would (a fused prior: its circle, and its roll while
        #: fusion has measured it; a system's own seed: what that pose decided).
        self._prior_decided: dict[str, tuple[bool, bool]] = {}
        self._received = self._processed = self._dropped = self._stale = 0
        self._frame_problem: str | None = None
        self._camera_fault: str | None = None
        self._fingerprint: int | None = None
        self._repeated_since: Frame | None = None  # the first frame of a run of equal images
        self._faults = 0
        self._fault: str | None = None
        self._records: list[VisionRecord | LoggedImage] = []
        self._last_logged_image = -math.inf
        self._status: VisionStatus | None = None

    # --- inputs ---------------------------------------------------------------------------
    def begin(self, t0: float) -> None:
        """The trial starts at ``t0``: records are timed from it."""
        self.t0 = t0

    def publish_state(self, sample: StateSample) -> None:
        """The arm's and the track's state at a control tick (for ``X_CM`` at capture)."""
        self.history.add(sample)

    def on_frame(self, frame: Frame, now: float) -> None:
        """The camera's newest frame. An unusable one is counted and named, never processed."""
        self._status = None
        problem = frame_problem(frame)
        if problem is not None:
            self._frame_problem = f"corrupt frame {frame.seq}: {problem}"
            return
        self._frame_problem = None
        if self._newest is not None and frame.seq <= self._newest.seq:
            return  # the camera handed the same frame twice: nothing new
        if self._frozen(frame):
            return
        if self._newest is not None and not self._newest_taken:
            self._dropped += 1
        self._newest, self._newest_taken = frame, False
        self._received += 1
        log_every = self.config.log_frames_every_s
        if log_every > 0 and frame.stamp - self._last_logged_image >= log_every:
            self._records.append(LoggedImage(frame.stamp, encode_image(frame.image)))
            self._last_logged_image = frame.stamp

    def _frozen(self, frame: Frame) -> bool:
        """Whether ``frame`` shows the camera is not live (and latch why)."""
        if self._camera_fault is not None:
            return True
        previous = self._newest
        fingerprint = image_fingerprint(frame.image)
        repeated = fingerprint == self._fingerprint
        self._fingerprint = fingerprint
        if previous is not None and frame.stamp <= previous.stamp:
            self._camera_fault = (
                f"frame {frame.seq} stamped {frame.stamp - self.t0:.3f} s, not after frame "
                f"{previous.seq} at {previous.stamp - self.t0:.3f} s"
            )
        elif not repeated or previous is None:
            self._repeated_since = frame
        else:
            first = self._repeated_since or previous
            moved = self._motion(first.stamp, frame.stamp)
            if moved is not None:
                self._camera_fault = (
                    f"frozen camera: frame {frame.seq} repeats the image of frame {first.seq} "
                    f"though the camera moved {1000 * moved[0]:.0f} mm, {moved[1]:.1f}° since"
                )
        return self._camera_fault is not None

    def _motion(self, since: float, until: float) -> tuple[float, float] | None:
        """(m, deg) the camera moved relative to the carriage between two stamps, when that is
        more than the repeat thresholds; None when less or not known."""
        before, after = self.history.X_CM_at(since), self.history.X_CM_at(until)
        if before is None or after is None:
            return None
        moved_m = float(np.linalg.norm(after.p - before.p))
        cosine = (np.trace(before.R.T @ after.R) - 1.0) / 2.0
        turned_deg = math.degrees(math.acos(float(np.clip(cosine, -1.0, 1.0))))
        config = self.config
        if moved_m > config.repeat_motion_m or turned_deg > config.repeat_motion_deg:
            return moved_m, turned_deg
        return None

    def step(self, now: float) -> None:
        """Fuse the results that are done by ``now``, then hand the newest frame to every free
        system that has not seen it."""
        for result in self.workers.finished(now):
            self._ingest(result, now)
        frame = self._newest
        if frame is None:
            return
        X_CM = self.history.X_CM_at(frame.stamp)
        fused_prior = None if X_CM is None else self.fusion.prior_X_CT(X_CM, frame.stamp)
        idle = self.workers.idle()
        free_slots = self.slots - sum(1 for s in self.systems if self._holds_slot(s, now))
        if free_slots < len(idle):  # taking turns: the longest waiting first
            idle = sorted(idle, key=self._last_start.__getitem__)
        for system in idle:
            if free_slots <= 0:
                break
            if frame.seq <= self._last_seq[system]:
                continue
            prior = fused_prior if fused_prior is not None else self._seed(system, X_CM, frame)
            # A frame that would be stale before the system is done with it is not worth taking
            # (a search without any prior is: its pose seeds the next one).
            duration = self._expected_s(system, acquiring=prior is None)
            if prior is not None and now - frame.stamp + duration > self.config.max_frame_age_s:
                self._last_seq[system] = frame.seq  # passed up for good: it only gets older
                self._fade(system)
                continue
            deadline = None
            if fused_prior is not None:
                # With a track to act on, a failed track's fallback search (whose own pose no
                # longer seeds anything) must end before the frame is too old, or not start.
                searching = self._expected_s(system, acquiring=True)
                deadline = frame.stamp + self.config.max_frame_age_s - searching
            job = VisionJob(system, frame, prior, now, deadline)
            self._prior_decided.pop(system, None)
            if fused_prior is not None:
                self._prior_decided[system] = (self.fusion.roll_measured(frame.stamp), True)
            elif prior is not None:
                self._prior_decided[system] = self._seeds[system][2]
            self.workers.start(job)
            self._running[system] = job
            free_slots -= 1
            self._last_seq[system] = frame.seq
            self._last_start[system] = now
            if not self._newest_taken:
                self._newest_taken = True
                self._processed += 1
            self._status = None

    # --- outputs --------------------------------------------------------------------------
    def latest(self) -> VisionStatus:
        if self._status is None:
            self._status = VisionStatus(
                fusion=self.fusion.state(),
                frames_received=self._received,
                frames_processed=self._processed,
                frames_dropped=self._dropped,
                results_stale=self._stale,
                newest_frame_stamp=None if self._newest is None else self._newest.stamp,
                frame_problem=self._frame_problem,
                estimator_faults=self._faults,
                estimator_fault=self._fault,
                camera_fault=self._camera_fault,
            )
        return self._status

    def drain(self) -> list[VisionRecord | LoggedImage]:
        """The records (and images to keep) since the last call, for the trial log."""
        records, self._records = self._records, []
        return records

    def close(self) -> None:
        self.workers.close()

    # --- internals ------------------------------------------------------------------------
    def _holds_slot(self, system: str, now: float) -> bool:
        """Whether ``system`` is busy on a result still worth a slot. A tracking job whose frame
        is already older than ``max_frame_age_s`` will be discarded when it comes (a failed
        track that falls back to a search can take 150–250 ms): the next system may start
        beside it rather than wait for nothing."""
        job = self._running.get(system)
        if job is None:
            return False
        doomed = job.prior_X_CT is not None and now - job.frame.stamp > self.config.max_frame_age_s
        return not doomed

    def _expected_s(self, system: str, *, acquiring: bool) -> float:
        """How long ``system`` may take over a frame: the modelled time, or what its last frame
        took when that was longer (on a busy machine, much longer), plus its frame-to-frame
        variation: a frame that would be finished in time only if this one goes as fast as the
        last is a coin toss between a result and a stale one (which costs a slot's time too)."""
        modelled = self.config.processing_s(system, acquiring=acquiring)
        mode = (system, acquiring)
        recent = self._took.get(mode, 0.0) + self._jitter.get(mode, 0.0)
        return max(modelled, recent)

    def _fade(self, system: str) -> None:
        """Each frame ``system`` passes up makes its recent time count a little less: on a
        machine that has since got less busy it gets to try again."""
        mode = (system, False)
        if mode in self._took:
            self._took[mode] *= 0.97

    def _seed(self, system: str, X_CM: Pose | None, frame: Frame) -> Pose | None:
        """``system``'s own latest pose carried to ``frame``'s capture, if recent enough."""
        seed = self._seeds.get(system)
        if seed is None or X_CM is None or frame.stamp - seed[0] > SEED_MAX_AGE_S:
            return None
        return X_CM @ seed[1]

    def _ingest(self, result: VisionResult, now: float) -> None:
        self._status = None
        job, m = result.job, result.measurement
        self._running.pop(job.system, None)
        mode = (job.system, job.prior_X_CT is None)
        if mode in self._took:
            change = abs(result.processing_s - self._took[mode])
            self._jitter[mode] = 0.75 * self._jitter.get(mode, 0.0) + 0.25 * change
        self._took[mode] = result.processing_s
        capture = job.frame.stamp
        decided = self._prior_decided.pop(job.system, None)
        if decided is not None:
            m = honest(m, *decided)
        if m.valid and m.prior is not None:
            X_CM = self.history.X_CM_at(capture)
            if X_CM is not None:
                self._seeds[job.system] = (capture, X_CM.inverse() @ m.prior, decided_parts(m))
        if result.error is not None:
            self._faults += 1
            self._fault = result.error
        outcome: VisionOutcome
        fused_at = None
        if now - capture > self.config.max_frame_age_s:
            self._stale += 1
            outcome = "stale"
            reason = (
                f"frame {1000 * (now - capture):.0f} ms old when the result came "
                f"(max_frame_age_s {self.config.max_frame_age_s})"
            )
        else:
            outcome, reason, fused_at = self._fuse(m, capture, now)
        truth = job.frame.truth
        self._records.append(
            VisionRecord(
                t=now - self.t0,
                system=job.system,
                seq=job.frame.seq,
                capture_t=capture - self.t0,
                arrival_t=None
                if job.frame.arrival_stamp is None
                else job.frame.arrival_stamp - self.t0,
                started_t=job.started - self.t0,
                finished_t=result.finished - self.t0,
                outcome=outcome,
                measurement=m,
                reason=reason,
                fused_at_t=None if fused_at is None else fused_at - self.t0,
                processing_ms=1000.0 * result.processing_s,
                truth_X_CT=None if truth is None else truth.X_CT,
            )
        )

    def _fuse(
        self, m: Measurement, capture: float, now: float
    ) -> tuple[VisionOutcome, str, float | None]:
        """Apply ``m`` at its capture stamp (or, for comparison, at ``now``): outcome, reason,
        and the stamp it was applied at."""
        stamp = capture if self.config.fuse_at == "capture" else now
        X_CM = self.history.X_CM_at(stamp)
        if X_CM is None:
            return "rejected", "no arm/track state at the stamp it would be applied at", None
        if stamp != m.stamp:
            m = dataclasses.replace(m, stamp=stamp)
        estimate = self.fusion.update([m], X_CM, stamp)
        if m.system in estimate.accepted:
            return "accepted", "", stamp
        for system, why in estimate.rejected:
            if system == m.system:
                return "rejected", why, stamp
        for system, why in estimate.not_measured:
            if system == m.system:
                return "not_measured", why, stamp
        return "rejected", "fusion did not use it", stamp


def drain_images(items: Iterable[VisionRecord | LoggedImage]) -> tuple[list, list]:
    """Split drained items into (vision records, images)."""
    records, images = [], []
    for item in items:
        (images if isinstance(item, LoggedImage) else records).append(item)
    return records, images
