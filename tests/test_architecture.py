"""The package layout's rules, checked on the source: no import cycles, and dependencies that point
down the flow audio -> face -> models / datasets -> output -> pipeline -> training -> evaluation ->
serve -> cli only (docs/architecture.md). Every ``import`` counts, also those inside functions:
a lazy import hides a cycle from Python, not from a reader."""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

# unit -> level; a module may import its own unit and units of a lower level only. A unit is a
# subpackage of talkmesh or a top-level module. Equal levels (models, datasets) may not import
# each other. The root package (talkmesh/__init__.py) is the public facade: nothing inside imports it.
LEVELS: dict[str, int] = {
    "errors": 0,
    "constants": 0,
    "version": 0,
    "heap": 0,
    "blas": 0,
    "cache": 0,
    "forked": 0,
    "safe_load": 1,
    "config": 1,
    "animation": 1,
    "audio": 2,
    "face": 3,
    "models": 4,
    "datasets": 4,
    "output": 5,
    "pipeline": 6,
    "retarget": 6,
    "training": 7,
    "batch": 7,
    "evaluation": 8,
    "serve": 9,
    "cli": 10,
    "__main__": 11,
}
FACADE = "talkmesh"


def module_name(path: Path, src: Path) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def import_graph(src: Path) -> dict[str, set[str]]:
    """module -> the talkmesh modules it imports (``from pkg import name`` is ``pkg.name`` when
    that is a module, else ``pkg``)."""
    files = {module_name(p, src): p for p in (src / "talkmesh").rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.split(".")[0] == "talkmesh")
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative import: resolve against this module's package
                    base = name.split(".") if is_package else name.split(".")[:-1]
                    base = base[: len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "talkmesh":
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    deps.add(sub if sub in files else target)
        deps.discard(name)
        graph[name] = {d for d in deps if d in files}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules (first == last), or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        colour[node] = GREY
        stack.append(node)
        for dep in sorted(graph[node]):
            if colour[dep] == GREY:
                return stack[stack.index(dep) :] + [dep]
            if colour[dep] == WHITE and (cycle := visit(dep)):
                return cycle
        stack.pop()
        colour[node] = BLACK
        return None

    for node in sorted(graph):
        if colour[node] == WHITE and (cycle := visit(node)):
            return cycle
    return None


def unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else FACADE


def direction_violations(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for module, deps in sorted(graph.items()):
        a = unit(module)
        for dep in sorted(deps):
            b = unit(dep)
            if a == b or a == FACADE:
                continue
            if b == FACADE:
                bad.append(f"{module} imports the facade {dep}")
            elif a not in LEVELS or b not in LEVELS:
                bad.append(f"{module} -> {dep}: add the unit to LEVELS (docs/architecture.md)")
            elif LEVELS[b] >= LEVELS[a]:
                bad.append(f"{module} -> {dep}: {a} may not import {b}")
    return bad


def test_no_import_cycle():
    cycle = find_cycle(import_graph(SRC))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_dependencies_point_down_the_flow():
    assert direction_violations(import_graph(SRC)) == []


@pytest.mark.parametrize("forbidden", ["training", "evaluation", "cli", "serve"])
def test_models_import_no_training_evaluation_cli_or_serve(forbidden):
    graph = import_graph(SRC)
    hits = [
        (m, d)
        for m, deps in graph.items()
        if unit(m) == "models"
        for d in deps
        if unit(d) == forbidden
    ]
    assert hits == []


def test_serve_does_not_import_cli():
    graph = import_graph(SRC)
    assert not [m for m, deps in graph.items() if unit(m) == "serve" and "talkmesh.cli" in deps]


def test_checker_finds_a_planted_cycle_and_a_wrong_way_import(tmp_path):
    """The checks can fail: a temporary copy of src/ with a cycle and an upward import planted."""
    copy = tmp_path / "src"
    shutil.copytree(
        SRC / "talkmesh", copy / "talkmesh", ignore=shutil.ignore_patterns("data", "static")
    )
    assert find_cycle(import_graph(copy)) is None
    errors = copy / "talkmesh" / "errors.py"
    # a lazy import inside a function still counts
    errors.write_text(
        errors.read_text() + "\n\ndef _planted():\n    from talkmesh.audio import loading\n"
    )
    loading = copy / "talkmesh" / "audio" / "loading.py"
    loading.write_text(loading.read_text() + "\nimport talkmesh.errors\n")
    cycle = find_cycle(import_graph(copy))
    assert cycle is not None and "talkmesh.errors" in cycle and "talkmesh.audio.loading" in cycle
    assert any("errors may not import audio" in v for v in direction_violations(import_graph(copy)))
    models = copy / "talkmesh" / "models" / "release.py"
    models.write_text(models.read_text() + "\nfrom talkmesh.training import trainer\n")
    assert any(
        "models may not import training" in v for v in direction_violations(import_graph(copy))
    )


MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 80
LONG_REASON = "long because"  # a longer function's docstring says why, with these words


def size_violations(src: Path) -> list[str]:
    """Modules over MAX_MODULE_LINES lines; functions over MAX_FUNCTION_LINES lines whose
    docstring does not say why ("... long because ...")."""
    bad = []
    for path in sorted((src / "talkmesh").rglob("*.py")):
        text = path.read_text()
        rel = path.relative_to(src)
        if (n := len(text.splitlines())) > MAX_MODULE_LINES:
            bad.append(f"{rel}: {n} lines")
        for node in ast.walk(ast.parse(text, str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                doc = (ast.get_docstring(node) or "").lower()
                if n > MAX_FUNCTION_LINES and LONG_REASON not in doc:
                    bad.append(f"{rel}:{node.lineno} {node.name}(): {n} lines")
    return bad


def test_modules_and_functions_are_short():
    assert size_violations(SRC) == []


def test_size_check_can_fail(tmp_path):
    pkg = tmp_path / "talkmesh"
    pkg.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))
    (pkg / "long.py").write_text(
        f"def f():\n{body}\n\n\ndef g():\n    '''Long because: a table.'''\n{body}\n"
    )
    assert size_violations(tmp_path) == [f"talkmesh/long.py:1 f(): {MAX_FUNCTION_LINES + 1} lines"]
    (pkg / "big.py").write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    assert f"talkmesh/big.py: {MAX_MODULE_LINES + 1} lines" in size_violations(tmp_path)


MODELS = SRC / "talkmesh" / "models"


def family_folders(models: Path) -> set[str]:
    """The folders of talkmesh/models: one per model family (docs/adding-a-model.md)."""
    return {p.parent.name for p in models.glob("*/__init__.py")}


def family_violations(graph: dict[str, set[str]], families: set[str]) -> list[str]:
    """A family folder imports the shared models modules and its own files, never another
    family; the shared modules reach a family only through the registry's names."""

    def family(module: str) -> str | None:
        parts = module.split(".")
        return (
            parts[2] if len(parts) > 2 and parts[1] == "models" and parts[2] in families else None
        )

    bad = []
    for module, deps in sorted(graph.items()):
        if unit(module) != "models" or module == "talkmesh.models":
            continue
        for dep in sorted(deps):
            if unit(dep) == "models" and family(dep) not in (None, family(module)):
                who = f"the {family(module)} family" if family(module) else "a shared module"
                bad.append(f"{module} -> {dep}: {who} may not import the {family(dep)} family")
    return bad


def test_one_folder_per_family_in_the_registry():
    from talkmesh.models.registry import FAMILY_MODELS, family_package

    assert family_folders(MODELS) == set(FAMILY_MODELS)
    assert all(family_package(f) == f"talkmesh.models.{f}" for f in FAMILY_MODELS)
    # names that carry a family belong in its folder
    flat = {p.stem for p in MODELS.glob("*.py")}
    assert not [n for n in flat for f in FAMILY_MODELS if n.startswith(f) or n.endswith(f)]


def test_families_import_only_shared_modules_and_their_own_folder():
    assert family_violations(import_graph(SRC), family_folders(MODELS)) == []


def test_family_check_can_fail(tmp_path):
    copy = tmp_path / "src"
    shutil.copytree(
        SRC / "talkmesh", copy / "talkmesh", ignore=shutil.ignore_patterns("data", "static")
    )
    voca = copy / "talkmesh" / "models" / "voca" / "model.py"
    voca.write_text(voca.read_text() + "\nfrom talkmesh.models.codetalker.vq import VQConfig\n")
    layers = copy / "talkmesh" / "models" / "layers.py"
    layers.write_text(layers.read_text() + "\nimport talkmesh.models.meshtalk.prior\n")
    bad = family_violations(import_graph(copy), family_folders(copy / "talkmesh" / "models"))
    assert bad == [
        "talkmesh.models.layers -> talkmesh.models.meshtalk.prior: a shared module may not "
        "import the meshtalk family",
        "talkmesh.models.voca.model -> talkmesh.models.codetalker.vq: the voca family may not "
        "import the codetalker family",
    ]
