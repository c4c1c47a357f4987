"""Build an estimator by system name; the CLI, the matrix runner and the loop use this."""

from __future__ import annotations

import importlib
from typing import Any

from estimators.frame import CameraInfo
from estimators.measurement import SYSTEMS, Estimator
from estimators.target import TargetModel

#: system name → "module:factory"; a factory takes (target, camera, **options).
_FACTORIES = {
    "corners": "estimators.corners:build",
    "lines": "estimators.lines:build",
    "ellipses": "estimators.ellipses:build",
}


def build_estimator(
    system: str, target: TargetModel, camera: CameraInfo, **options: Any
) -> Estimator:
    """An estimator for ``system`` tracking ``target``.

    ``system`` is one of corners, lines, ellipses — or a ``"module:factory"`` path, which lets
    tests and experiments plug in their own estimator.
    """
    if system not in _FACTORIES and ":" not in system:
        raise ValueError(f"unknown estimator system {system!r}; choose from {', '.join(SYSTEMS)}")
    module_name, factory_name = _FACTORIES.get(system, system).split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise NotImplementedError(f"the {system} estimator is not implemented yet") from exc
        raise
    return getattr(module, factory_name)(target, camera, **options)
