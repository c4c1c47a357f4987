"""The layer contract (DESIGN.md): imports go down, never up, and no two layers import each other.

    hil  →  sim_backends  →  configuration  →  drivers  →  estimators

and inside ``hil``: cli → progress → analysis → runtime | evaluation → logs (runtime and
evaluation are siblings that never import each other). Every import counts, including those
inside functions, so a lazy import cannot hide an upward dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Top-level packages from the bottom of the stack up.
LAYERS = ("estimators", "drivers", "configuration", "sim_backends", "hil")
#: Sub-packages of hil from the bottom up; a tuple holds siblings that must not import each other.
HIL_LAYERS = (
    ("hil.logs",),
    ("hil.runtime", "hil.evaluation"),
    ("hil.analysis",),
    ("hil.progress",),
    ("hil.cli",),
)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in a file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


def _layer(module: str) -> int | None:
    top = module.split(".")[0]
    return LAYERS.index(top) if top in LAYERS else None


def _hil_layer(module: str) -> tuple[int, str] | None:
    for rank, siblings in enumerate(HIL_LAYERS):
        for name in siblings:
            if module == name or module.startswith(name + "."):
                return rank, name
    return None


def layer_violations(root: Path = ROOT) -> list[str]:
    """Every import that goes up a layer or sideways between sibling layers."""
    problems = []
    for package in LAYERS:
        for path in sorted((root / package).rglob("*.py")):
            module = ".".join(path.relative_to(root).with_suffix("").parts)
            own = _layer(module)
            own_hil = _hil_layer(module)
            for line, imported in _imports(path):
                where = f"{path.relative_to(root)}:{line} imports {imported}"
                other = _layer(imported)
                if other is not None and other > own:
                    problems.append(f"{where} (upward: {LAYERS[own]} is below {LAYERS[other]})")
                    continue
                other_hil = _hil_layer(imported)
                if own_hil is None or other_hil is None or own_hil[1] == other_hil[1]:
                    continue
                if other_hil[0] > own_hil[0]:
                    problems.append(f"{where} (upward inside hil)")
                elif other_hil[0] == own_hil[0]:
                    problems.append(
                        f"{where} (sideways: {own_hil[1]} and {other_hil[1]} are siblings)"
                    )
    return problems


def test_imports_go_down_the_layers():
    problems = layer_violations()
    assert not problems, "layer contract broken:\n" + "\n".join(problems)


@pytest.mark.parametrize(
    ("module", "source", "expected"),
    [
        ("estimators/bad.py", "from hil.runtime.loop import ApproachLoop\n", "upward"),
        ("drivers/bad.py", "def f():\n    import sim_backends.arm\n", "upward"),
        ("hil/logs/bad.py", "from hil.analysis.report import make_report\n", "upward inside hil"),
        ("hil/runtime/bad.py", "from hil.evaluation.matrix import run_matrix\n", "sideways"),
    ],
)
def test_layer_contract_catches_an_upward_import(tmp_path, module, source, expected):
    for package in LAYERS:
        (tmp_path / package).mkdir()
    path = tmp_path / module
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(source, encoding="utf-8")
    problems = layer_violations(tmp_path)
    assert len(problems) == 1 and expected in problems[0], problems


def test_layer_contract_allows_downward_imports(tmp_path):
    for package in LAYERS:
        (tmp_path / package).mkdir()
    (tmp_path / "hil" / "analysis").mkdir()
    (tmp_path / "hil" / "analysis" / "ok.py").write_text(
        "from hil.logs.triallog import TrialLog\nfrom hil.runtime.trial import SimTrial\n"
        "from sim_backends.arm import SimArm\nfrom estimators.frame import Frame\n",
        encoding="utf-8",
    )
    assert layer_violations(tmp_path) == []
