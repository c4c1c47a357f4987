"""Loading YAML into frozen pydantic models, with errors that name the file, field and line.

Built-in configurations ship in ``configs/`` (installed as the package ``satgrasp_configs``), so
a name such as ``reference`` resolves the same from any working directory; anything that looks
like a path is read from disk instead.
"""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

os.environ.setdefault("PYDANTIC_ERRORS_INCLUDE_URL", "0")

ModelT = TypeVar("ModelT", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration file could not be read or did not validate.

    The message names the file and, per problem, the field path, its YAML line and what was
    expected, e.g. ``configs/mockup.yaml: marman_ring.outer_diameter (line 12): Input should
    be greater than 0``.
    """

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = problems
        lines = "\n".join(f"  {p}" for p in problems)
        super().__init__(f"invalid configuration {source}:\n{lines}")

    def __reduce__(self):
        # Raised in a worker process, it crosses back pickled: rebuilt from its own fields
        # (the default rebuilds from the message alone and fails, breaking the whole pool).
        return (type(self), (self.source, self.problems))


def builtin_config_dir() -> Path:
    """Directory holding the built-in YAML files (the repository's ``configs/``).

    ``configs/`` is installed as the data-only namespace package ``satgrasp_configs``; an
    editable install adds a placeholder entry to its path, so take the first real directory.
    """
    spec = importlib.util.find_spec("satgrasp_configs")
    for location in (spec.submodule_search_locations or []) if spec else []:
        if Path(location, "mockup.yaml").is_file():
            return Path(location)
    raise ConfigError("satgrasp_configs", ["built-in configurations not found; reinstall satgrasp"])


def builtin_names(subdir: str = "") -> list[str]:
    """Names (file stems) of the built-in configurations in ``configs/<subdir>``."""
    folder = builtin_config_dir() / subdir
    return sorted(p.stem for p in folder.glob("*.yaml"))


def looks_like_path(name_or_path: str | os.PathLike[str]) -> bool:
    """Whether a configuration is named by a path (``my_mockup.yaml``, ``rigs/lab``) rather
    than by a built-in name (``reference``)."""
    text = str(name_or_path)
    return text.endswith((".yaml", ".yml")) or os.sep in text or "/" in text


def relative_to_file(path: Path, config_file: Path) -> Path:
    """``path`` as named inside ``config_file``: a relative one is taken from the directory of
    that file, not from the working directory, so a configuration reads the same from
    anywhere."""
    path = path.expanduser()
    return path if path.is_absolute() else (config_file.parent / path).resolve()


def named_in_file(name_or_path: str, config_file: Path, field: str) -> str:
    """A configuration that ``config_file`` names in ``field``: a built-in name as it is, a
    path taken relative to ``config_file`` (``relative_to_file``). A path to no file raises
    ``ConfigError`` naming ``config_file``, the field and where it looked."""
    if not looks_like_path(name_or_path):
        return name_or_path
    path = relative_to_file(Path(name_or_path), config_file)
    if not path.is_file():
        raise ConfigError(
            str(config_file),
            [f"{field}: file not found: {path} (a relative path is taken from this file's folder)"],
        )
    return str(path)


def resolve_config_path(name_or_path: str | os.PathLike[str], subdir: str = "") -> Path:
    """A built-in name (``reference``) or a path to a YAML file → an existing file path."""
    text = str(name_or_path)
    if looks_like_path(text):
        path = Path(text).expanduser()
        if not path.is_file():
            raise ConfigError(text, ["file not found"])
        return path
    candidate = builtin_config_dir() / subdir / f"{text}.yaml"
    if candidate.is_file():
        return candidate
    known = ", ".join(builtin_names(subdir)) or "(none)"
    raise ConfigError(text, [f"no built-in configuration named {text!r}; known: {known}"])


def _line_index(node: yaml.Node, path: tuple[Any, ...] = ()) -> Iterator[tuple[tuple, int]]:
    """(field path, 1-based line) for every node of a composed YAML document."""
    yield path, node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            key = key_node.value
            yield (*path, key), key_node.start_mark.line + 1
            for sub_path, line in _line_index(value_node, (*path, key)):
                if sub_path != (*path, key):
                    yield sub_path, line
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            yield from _line_index(item, (*path, i))


def _format_errors(error: ValidationError, lines: dict[tuple, int]) -> list[str]:
    problems = []
    for item in error.errors():
        loc = tuple(part for part in item["loc"] if not str(part).startswith("function-"))
        field = ".".join(str(part) for part in loc) or "(top level)"
        line = None
        for cut in range(len(loc), -1, -1):  # nearest ancestor present in the file
            line = lines.get(loc[:cut])
            if line is not None:
                break
        where = f" (line {line})" if line is not None else ""
        message = item["msg"].removeprefix("Value error, ")
        if item["type"] == "extra_forbidden":
            message = "unknown key (check its spelling; unknown keys are not allowed)"
        elif item["type"] == "missing":
            message = "required field is missing"
        elif "input" in item and item["type"] not in ("value_error", "assertion_error"):
            message = f"{message} (got {item['input']!r})"
        problems.append(f"{field}{where}: {message}")
    return problems


def parse_yaml_text(text: str, model: type[ModelT], source: str) -> ModelT:
    """Validate YAML text into ``model``; errors name ``source``, the field and its line."""
    try:
        data = yaml.safe_load(text)
        node = yaml.compose(text)
    except yaml.YAMLError as exc:
        raise ConfigError(source, [f"not valid YAML: {exc}"]) from exc
    if data is None:
        raise ConfigError(source, ["the file is empty"])
    if not isinstance(data, dict):
        raise ConfigError(
            source, [f"expected a mapping at the top level; got {type(data).__name__}"]
        )
    lines = dict(_line_index(node)) if node is not None else {}
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(source, _format_errors(exc, lines)) from None


def load_config(
    name_or_path: str | os.PathLike[str], model: type[ModelT], subdir: str = ""
) -> ModelT:
    """Load a built-in configuration by name, or a YAML file by path, into ``model``."""
    path = resolve_config_path(name_or_path, subdir)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror}"]) from exc
    return parse_yaml_text(text, model, str(path))
