"""A simulated trial (``configs/sim.yaml``): which mock-up, camera, rig and estimators, the
image noise, the randomised start and the fusion settings.

Every model is frozen and rejects unknown keys.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import Field, ValidationError, field_serializer, model_validator

from configuration.approach import ApproachConfig
from configuration.base import PositiveM, Strict, Vec3
from configuration.devices import DevicesConfig
from configuration.files import load_config, named_in_file, resolve_config_path
from configuration.render import NoiseConfig, RenderConfig
from configuration.vision import CameraTiming, VisionConfig
from estimators.fusion import FusionParams


class StartConfig(Strict):
    """Randomised start of a simulated approach, as in the reference study: the camera
    ``distance_m`` in front of the ring face, up to ``max_offset_m`` off the ring axis
    (sideways and up/down) and turned up to ``max_rotation_deg`` about each of its axes; the
    mock-up sits on its carriage misaligned by up to ``mount_misalignment_deg``."""

    distance_m: PositiveM = 2.5
    max_offset_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.3
    max_rotation_deg: Annotated[float, Field(ge=0.0, le=30.0)] = 10.0
    mount_misalignment_deg: Annotated[float, Field(ge=0.0, le=10.0)] = 1.0


#: How a trial's time passes (``SimulationConfig.clock``).
ClockKind = Literal["sim", "wall"]
#: How the track and gripper drivers reach their simulated devices (``SimulationConfig.links``).
LinkKind = Literal["direct", "tcp"]


#: The faults a simulated trial can be given (docs/faults.md).
FaultKind = Literal[
    "camera_dropout",
    "frozen_camera",
    "corrupt_frame",
    "nan_estimate",
    "protective_stop",
    "emergency_stop",
    "link_drop",
    "modbus_silent",
    "track_fault",
    "tumbling_target",
    "disk_full",
]
FAULT_KINDS: tuple[str, ...] = FaultKind.__args__  # type: ignore[attr-defined]


class FaultConfig(Strict):
    """A fault injected into a simulated trial: ``kind`` at ``at_s`` seconds after the start,
    or ``after_s`` seconds after the trial first enters ``phase``. ``rate_deg_s``: how a
    ``tumbling_target`` turns about its own axes.

    camera_dropout: no more frames; frozen_camera: the last image again and again with new
    stamps; corrupt_frame: one truncated image; nan_estimate: every estimator returns NaN from
    then on; protective_stop / emergency_stop: the arm's controller halts; link_drop: the arm
    stops answering; modbus_silent: the track's Modbus device stops answering; track_fault: the
    track's drive faults; tumbling_target: the mock-up starts turning; disk_full: the trial
    log's writes fail (an injected ENOSPC)."""

    kind: FaultKind
    at_s: Annotated[float, Field(ge=0.0)] | None = None
    phase: Literal["acquire", "approach", "standoff", "grasp", "retreat"] | None = None
    after_s: Annotated[float, Field(ge=0.0)] = 0.0
    rate_deg_s: Vec3 = (0.0, 3.0, 0.0)

    @model_validator(mode="after")
    def _when(self) -> FaultConfig:
        if (self.at_s is None) == (self.phase is None):
            raise ValueError(f"fault {self.kind}: give either at_s or phase (with after_s)")
        return self


class SimulationConfig(Strict):
    """Everything a simulated trial needs (``configs/sim.yaml``). ``mockup``, ``camera`` and
    ``rig`` name built-in configurations or YAML files (a relative path is taken from the
    directory of the file that names it: ``load_simulation``)."""

    name: str
    mockup: str = "default"
    camera: str = "reference"
    rig: str = "rig"
    #: Estimators: corners, lines, ellipses (or a "module:factory" path for experiments).
    systems: list[str] = Field(default_factory=lambda: ["corners", "lines", "ellipses"])
    noise: NoiseConfig = NoiseConfig(preset="low")
    #: Anti-aliased (``supersample: auto``) wherever the noise is too small to hide a
    #: point-sampled image's staircase edges (``RenderConfig.for_noise``).
    render: RenderConfig = RenderConfig(supersample="auto")
    #: How the loop's time passes: ``sim`` steps the world as fast as the machine allows and
    #: charges vision its modelled time (deterministic: CI, campaigns, the demo); ``wall`` runs
    #: the simulated world in real time in processes of its own, reached only through the device
    #: protocols, exactly as a rig would be.
    clock: ClockKind = "sim"
    camera_timing: CameraTiming = CameraTiming()
    vision: VisionConfig = VisionConfig()
    #: How the track and gripper drivers reach their simulated devices: in-process register
    #: access ("direct") or a real pymodbus server on 127.0.0.1 ("tcp").
    links: LinkKind = "direct"
    #: Which backend drives each device: every one simulated (default), the real drivers
    #: against loopback emulators of the simulated world, or the real rig (configuration.devices).
    devices: DevicesConfig = DevicesConfig()
    fusion: FusionParams = Field(default_factory=FusionParams)
    approach: ApproachConfig = ApproachConfig()
    start: StartConfig = StartConfig()
    #: Capture range of the (compliant) gripper around the grasp pose, and the object's width.
    grasp_capture_m: PositiveM = 0.01
    grasp_capture_deg: Annotated[float, Field(gt=0.0, le=20.0)] = 3.0
    grasp_object_width_m: PositiveM = 0.05
    #: Contact in simulation: the fingertips reach this far ahead of the camera along its
    #: optical axis (1 cm short of the ring's face at the default grasp pose, 0.35 m), and the
    #: mock-up's mount pushes back on them with this stiffness (N/m) once they pass its face.
    tool_reach_m: PositiveM = 0.34
    contact_stiffness: PositiveM = 2000.0
    max_duration_s: PositiveM = 150.0
    #: Faults injected into the simulated devices, the vision side or the log (``--clock sim``).
    faults: list[FaultConfig] = Field(default_factory=list)

    @field_serializer("fusion")
    def _fusion_as_dict(self, fusion: FusionParams) -> dict:
        values = {f.name: getattr(fusion, f.name) for f in dataclasses.fields(fusion)}
        values["covariance_scale"] = dict(fusion.covariance_scale)  # read-only mappings
        values["covariance_floor"] = {k: list(v) for k, v in fusion.covariance_floor.items()}
        return values

    @model_validator(mode="after")
    def _systems(self) -> SimulationConfig:
        if not self.systems:
            raise ValueError("systems: name at least one estimator")
        unknown = [
            s for s in self.systems if s not in ("corners", "lines", "ellipses") and ":" not in s
        ]
        if unknown:
            raise ValueError(
                f"systems: unknown estimator {unknown[0]!r} (corners, lines or ellipses)"
            )
        if len(set(self.systems)) != len(self.systems):
            raise ValueError("systems: each estimator at most once")
        if self.faults and self.clock != "sim":
            raise ValueError("faults: injected faults need clock: sim")
        return self


#: The fields of a simulation configuration that name other configuration files.
FILE_FIELDS = ("mockup", "camera", "rig")


def load_simulation(name_or_path: str | Path = "sim") -> SimulationConfig:
    """Load a simulated-trial configuration (``sim`` is ``configs/sim.yaml``). The mock-up,
    camera and rig it names by a relative path are found beside it (whatever the working
    directory), and held as absolute paths from then on."""
    path = resolve_config_path(name_or_path)
    config = load_config(path, SimulationConfig)
    files = {field: named_in_file(getattr(config, field), path, field) for field in FILE_FIELDS}
    return config.model_copy(update=files)


def with_overrides(config: SimulationConfig, **changes: object) -> SimulationConfig:
    """``config`` with top-level fields replaced (None leaves a field as it is), validated
    again — e.g. ``systems`` or ``noise`` from command-line options. Raises ``ValueError``
    naming each field that does not validate, on one line."""
    data = config.model_dump(mode="json")
    data.update({k: v for k, v in changes.items() if v is not None})
    try:
        return SimulationConfig.model_validate(data)
    except ValidationError as exc:
        raise ValueError(_one_line(exc)) from None


def with_light(config: SimulationConfig, light: str, seed: int) -> SimulationConfig:
    """``config`` under a named light (``configuration.random_mockup.named_lighting``):
    ``default``, ``harsh`` or ``random`` — a random mock-up's own random light (the one the
    matrix and the open-loop path use for it), else the light of ``seed``. ValueError naming
    the light otherwise."""
    from configuration.random_mockup import is_random_name, named_lighting, seed_of

    light_seed = seed_of(config.mockup) if is_random_name(config.mockup) else seed
    lighting = named_lighting(light, light_seed)
    return with_overrides(
        config, render=config.render.model_copy(update={"lighting": lighting}).model_dump()
    )


def with_settings(config: SimulationConfig, settings: list[str]) -> SimulationConfig:
    """``config`` with dotted settings applied, each ``key.path=value`` with the value read as
    YAML (``vision.fuse_at=arrival``, ``camera_timing.latency_s=0.1``), validated again.

    Raises ``ValueError`` naming the setting that is malformed or that does not validate.
    """
    data = config.model_dump(mode="json")
    for setting in settings:
        key, sep, text = setting.partition("=")
        path = [part for part in key.strip().split(".") if part]
        if not sep or not path:
            raise ValueError(f"--set {setting!r}: expected KEY=VALUE, e.g. vision.fuse_at=arrival")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ValueError(f"--set {setting!r}: the value is not valid YAML ({exc})") from None
        node = data
        for part in path[:-1]:
            child = node.get(part) if isinstance(node, dict) else None
            if not isinstance(child, dict):
                raise ValueError(f"--set {setting!r}: {part!r} is not a section of the config")
            node = child
        node[path[-1]] = value
    try:
        return SimulationConfig.model_validate(data)
    except ValidationError as exc:
        raise ValueError(f"--set {' '.join(settings)}: {_one_line(exc)}") from None


def _one_line(error: ValidationError) -> str:
    """``systems: unknown estimator 'x' (…); links: Input should be 'direct' or 'tcp'``."""
    problems = []
    for e in error.errors():
        field = ".".join(map(str, e["loc"]))
        message = e["msg"].removeprefix("Value error, ")
        problems.append(f"{field}: {message}" if field else message)
    return "; ".join(problems)
