"""Build an estimator by system name; the CLI, the matrix runner and the loop use this.

Every estimator the registry builds follows the intrinsics each frame carries
(``Frame.info``): a real camera reports its own calibration, which need not be the profile the
estimator was configured with. The system's estimator is built once per distinct
``CameraInfo`` (by content, ``CameraInfo.key``) on first sight and reused, so each built
estimator only ever sees frames of its own camera and precomputes what depends on it.
"""

from __future__ import annotations

import functools
import importlib
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from estimators.frame import CameraInfo, Frame
from estimators.geometry import Pose
from estimators.measurement import SYSTEMS, Estimator, Measurement
from estimators.target import TargetModel

#: system name → "module:factory"; a factory takes (target, camera, **options).
_FACTORIES = {
    "corners": "estimators.corners:build",
    "lines": "estimators.lines:build",
    "ellipses": "estimators.ellipses:build",
}

#: Distinct cameras kept built per system: a rig has one camera, a test a few profiles.
CAMERAS_KEPT = 4


class PerCameraEstimator:
    """An ``Estimator`` that hands each frame to the system's estimator built for that frame's
    ``CameraInfo``: built on first sight, then reused; the least recently used of more than
    ``capacity`` cameras is dropped (and rebuilt if its camera comes back)."""

    def __init__(
        self,
        build: Callable[[CameraInfo], Estimator],
        camera: CameraInfo,
        *,
        capacity: int = CAMERAS_KEPT,
    ):
        if capacity < 1:
            raise ValueError(f"capacity must be ≥ 1; got {capacity}")
        self._build = build
        self._capacity = capacity
        self._built: OrderedDict[tuple, Estimator] = OrderedDict()
        first = self.estimator_for(camera)  # a bad option or target fails here, not mid-run
        self.system: str = first.system

    @property
    def builds(self) -> int:
        """How many cameras are currently built (at most ``capacity``)."""
        return len(self._built)

    def estimator_for(self, camera: CameraInfo) -> Estimator:
        """The estimator built for ``camera``'s intrinsics (building it on first sight)."""
        key = camera.key
        estimator = self._built.get(key)
        if estimator is None:
            estimator = self._build(camera)
            self._built[key] = estimator
            if len(self._built) > self._capacity:
                self._built.popitem(last=False)
        else:
            self._built.move_to_end(key)
        return estimator

    def estimate(self, frame: Frame, prior_X_CT: Pose | None = None) -> Measurement:
        return self.estimator_for(frame.info).estimate(frame, prior_X_CT)


def _factory(system: str) -> Callable[..., Estimator]:
    if system not in _FACTORIES and ":" not in system:
        raise ValueError(f"unknown estimator system {system!r}; choose from {', '.join(SYSTEMS)}")
    module_name, factory_name = _FACTORIES.get(system, system).split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise NotImplementedError(f"the {system} estimator is not implemented yet") from exc
        raise
    return getattr(module, factory_name)


def build_estimator(
    system: str, target: TargetModel, camera: CameraInfo, **options: Any
) -> PerCameraEstimator:
    """An estimator for ``system`` tracking ``target``, following each frame's intrinsics.

    ``camera`` is the camera expected first (its estimator is built now, so bad options fail
    here). ``system`` is one of corners, lines, ellipses — or a ``"module:factory"`` path,
    which lets tests and experiments plug in their own estimator.
    """
    # A partial, not a lambda: the estimator pickles (to hand it to another process).
    return PerCameraEstimator(functools.partial(_factory(system), target, **options), camera)
