"""The import graph DESIGN.md promises: core <- stages <- app, only the named arrows between stages.

Every import counts, also the lazy ones inside functions: a lazy import of the app from a stage
is still a circle, only a slower one to notice.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("acquisition", "projector", "inference", "recon", "viewer", "twin", "mocks")
# the only arrows between stages (DESIGN.md, "Layout"); every stage may import core
ALLOWED = {
    ("mocks", "twin"), ("mocks", "acquisition"), ("mocks", "projector"),  # mocks stand in for hardware
    ("inference", "twin"),  # training data
    ("twin", "recon"),  # calibration and motion-compensation solvers the twin reuses
}
HARDWARE = ("gi", "linuxpy", "pygame", "serial")  # imported inside their driver, never at module level


def _package_of_file(path: Path) -> str:
    rel = path.relative_to(ROOT).parts
    if rel[0] == "gearscan":
        return "core" if len(rel) > 2 and rel[1] == "core" else "app"
    return rel[0]


def _package_of_module(name: str) -> str | None:
    parts = name.split(".")
    if parts[0] != "gearscan":
        return None
    if len(parts) > 1 and (parts[1] == "core" or parts[1] in STAGES):
        return parts[1]
    return "app"


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(module, line, at module level) of every import in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, node.lineno, id(node) in top))
        elif isinstance(node, ast.Import):
            out.extend((a.name, node.lineno, id(node) in top) for a in node.names)
    return out


def _sources() -> list[Path]:
    files = [p for d in ("gearscan", *STAGES) for p in (ROOT / d).rglob("*.py")]
    assert len(files) > 50, f"found only {len(files)} source files under {ROOT}"
    return files


def _edges() -> dict[tuple[str, str], list[str]]:
    edges: dict[tuple[str, str], list[str]] = {}
    for path in _sources():
        src = _package_of_file(path)
        for module, line, _ in _imports(path):
            dst = _package_of_module(module)
            if dst is not None and dst != src:
                edges.setdefault((src, dst), []).append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    return edges


def test_core_imports_no_other_gearscan_package() -> None:
    bad = [w for (src, _), where in _edges().items() if src == "core" for w in where]
    assert not bad, "gearscan.core must import only itself:\n" + "\n".join(bad)


def test_no_stage_imports_the_app() -> None:
    bad = [w for (src, dst), where in _edges().items() if dst == "app" and src != "app" for w in where]
    assert not bad, "stages and core must not import the app (gearscan/*.py):\n" + "\n".join(bad)


def test_only_the_designed_arrows_between_stages() -> None:
    bad = [w for (src, dst), where in _edges().items()
           if src in STAGES and dst in STAGES and (src, dst) not in ALLOWED for w in where]
    assert not bad, "imports between stages outside DESIGN.md's arrows:\n" + "\n".join(bad)


def test_no_package_circle() -> None:
    graph: dict[str, set[str]] = {}
    for src, dst in _edges():
        graph.setdefault(src, set()).add(dst)

    def reaches(a: str, b: str, seen: set[str]) -> bool:
        return any(n == b or (n not in seen and reaches(n, b, seen | {n})) for n in graph.get(a, ()))

    circles = sorted(p for p in graph if reaches(p, p, set()))
    assert not circles, f"packages on an import circle: {circles}"


def test_recon_and_core_stand_without_torch() -> None:
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in _sources() if _package_of_file(p) in ("recon", "core")
           for module, line, _ in _imports(p) if module.split(".")[0] == "torch"]
    assert not bad, "recon and core must work without torch:\n" + "\n".join(bad)


def test_hardware_libraries_are_imported_lazily() -> None:
    bad = [f"{p.relative_to(ROOT)}:{line} imports {module}" for p in _sources()
           for module, line, top in _imports(p) if top and module.split(".")[0] in HARDWARE]
    assert not bad, "hardware libraries at module level (import them inside the driver):\n" + "\n".join(bad)


def test_the_checks_can_fail(tmp_path) -> None:
    """The graph sees lazy imports too: a function-level import of the app from a stage is an edge."""
    stage = tmp_path / "recon"
    stage.mkdir()
    (stage / "x.py").write_text("def f():\n    from gearscan.replay import replay\n")
    assert [(m, top) for m, _, top in _imports(stage / "x.py")] == [("gearscan.replay", False)]
    assert _package_of_module("gearscan.replay") == "app"
    assert _package_of_module("gearscan.core.types") == "core"
    assert _package_of_module("gearscan.recon.measure") == "recon"


@pytest.mark.parametrize("name", ["Frame", "EncoderSample", "Burst", "PhaseResult", "Cloud", "Measurement"])
def test_results_that_cross_stages_are_frozen(name: str) -> None:
    from gearscan.core import types

    cls = getattr(types, name)
    assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, f"{name} must be a frozen dataclass"
