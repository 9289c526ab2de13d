"""The layout is the architecture: imports run downward only, no module imports itself back,
and docs/architecture.md names every module there is."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fem", "datamodules", "mammo_net")

#: Layers from the bottom; a module may import its own layer and the layers below it.
LAYERS = (
    "fem.contract",
    "fem.engine",
    "fem.breasts",
    "fem",  # the commands fem.cohort, fem.simulate, fem.mesh_breast
    "datamodules",
    "mammo_net",
    "",  # train.py, predict.py
)


def module_files() -> dict[str, Path]:
    """Dotted module name -> file, for the three packages and the two scripts."""
    files = {p.stem: ROOT / p for p in (Path("train.py"), Path("predict.py"))}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return files


def project_imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` imports, at any depth of its code (lazy imports too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        found |= {n for n in names if n in modules}
    return found


def layer(module: str) -> int:
    """Index in `LAYERS` of the deepest layer that holds ``module``."""
    top = module in ("train", "predict")
    return max(
        k
        for k, name in enumerate(LAYERS)
        if (top and name == "") or (name and (module == name or module.startswith(name + ".")))
    )


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    files = module_files()
    return {m: project_imports(p, set(files)) - {m} for m, p in files.items()}


def test_imports_run_downward(graph: dict[str, set[str]]) -> None:
    upward = [
        f"{m} ({LAYERS[layer(m)] or 'scripts'}) imports {d} ({LAYERS[layer(d)]})"
        for m, deps in graph.items()
        for d in sorted(deps)
        if layer(d) > layer(m)
    ]
    assert not upward, "\n".join(upward)


def test_no_import_cycle(graph: dict[str, set[str]]) -> None:
    def reaches(start: str) -> set[str]:
        seen, todo = set(), list(graph[start])
        while todo:
            m = todo.pop()
            if m not in seen:
                seen.add(m)
                todo.extend(graph.get(m, ()))
        return seen

    # a package's __init__ importing nothing, the cycle would be a module reaching itself
    cycles = sorted(m for m in graph if m in reaches(m))
    assert not cycles, f"modules on an import cycle: {cycles}"


def test_the_map_names_every_module() -> None:
    text = (ROOT / "docs" / "architecture.md").read_text()
    drawn = set(re.findall(r"\b((?:fem|datamodules|mammo_net)/[\w/]*\w\.py)\b", text))
    there = {
        str(p.relative_to(ROOT))
        for package in PACKAGES
        for p in (ROOT / package).rglob("*.py")
        if p.name != "__init__.py"
    }
    assert drawn == there, (
        f"in the code, not on the map: {sorted(there - drawn)}; "
        f"on the map, not in the code: {sorted(drawn - there)}"
    )
