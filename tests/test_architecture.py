"""The package's layers (docs/architecture.md): each module imports only from its own layer's package or from the
layers below it, never a private name of another module, and the modules form no import cycle."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "vid2sim"

#: bottom to top; a package may import the packages of the rows below its own
LAYERS = [
    ["runtime"],
    ["physics", "splats", "metrics", "meshing"],
    ["scene", "asset"],
    ["synthetic", "predictor"],
    ["reconstruct"],
    ["simulate", "evaluate", "export", "report"],
    ["apps"],
    ["cli"],
]
#: imports between packages of the same row that the layering allows (importer, imported)
SIBLINGS = {("splats", "metrics"), ("meshing", "metrics"), ("asset", "scene"), ("predictor", "synthetic")}
RANK = {package: rank for rank, row in enumerate(LAYERS) for package in row}
#: module-level exceptions, each with its reason
EXCEPTIONS = {("vid2sim.apps.bench.fuzz.runner", "vid2sim.cli"):
              "the reliability campaign drives the command line itself, as a user would (in a forked child)"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(path: Path) -> list[tuple[str, list[str], bool]]:
    """(module imported, names imported, inside a function or TYPE_CHECKING block) for each project import."""
    tree = ast.parse(path.read_text())
    found = []

    def visit(node: ast.AST, nested: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) or (
                isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test))
            if isinstance(child, ast.ImportFrom) and child.level == 0 and (child.module or "").startswith("vid2sim"):
                found.append((child.module, [a.name for a in child.names], inner))
            elif isinstance(child, ast.Import):
                found.extend((a.name, [], inner) for a in child.names if a.name.startswith("vid2sim"))
            visit(child, inner)

    visit(tree, False)
    return found


def _package(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_package_has_a_layer():
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert packages == set(RANK), packages ^ set(RANK)


def test_no_module_imports_a_layer_above_its_own():
    wrong = []
    for module, path in _modules().items():
        own = _package(module)
        if own is None or own == "__main__":  # the root package and the entry point
            continue
        for target, _, _ in _imports(path):
            other = _package(target)
            if other is None or other == own or (module, target) in EXCEPTIONS:
                continue
            if RANK[other] > RANK[own] or (RANK[other] == RANK[own] and (own, other) not in SIBLINGS):
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_no_module_imports_another_module_s_private_names():
    wrong = [f"{module} imports {name} from {target}" for module, path in _modules().items()
             for target, names, _ in _imports(path) if target != module
             for name in names if name.startswith("_") and not name.startswith("__")]
    assert not wrong, "\n".join(wrong)


def test_the_top_level_imports_form_no_cycle():
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for m, p in modules.items():
        edges = set()
        for target, names, nested in _imports(p):
            if nested:
                continue
            submodules = {f"{target}.{n}" for n in names} & set(modules)  # from package import module
            edges |= submodules or ({target} & set(modules))
        graph[m] = edges - {m}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, path: list[str]) -> bool:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle.extend(path + [node, nxt])
                return True
            if nxt not in state and visit(nxt, path + [node]):
                return True
        state[node] = 2
        return False

    for module in sorted(graph):
        if module not in state and visit(module, []):
            break
    assert not cycle, " -> ".join(cycle)


#: project imports that stay inside a function, each with its reason (importer, imported)
NESTED = {
    ("vid2sim.predictor.fem_truth", "vid2sim.predictor.data"):
        "predictor.data makes FEM shards with fem_truth, and fem_truth draws and writes samples with data's helpers",
    ("vid2sim.predictor.ensemble", "vid2sim.predictor.train"):
        "train reads ensembles, and an ensemble loads and evaluates its members with train's helpers",
    ("vid2sim.predictor.pretrain", "vid2sim.predictor.train"):
        "train runs pre-training first (pretrain_steps), and pre-training reuses train's split, schedule and video",
}
#: packages whose modules import the project inside functions, with the reason
NESTED_PACKAGES = {
    "vid2sim.apps.bench.fuzz": "the campaign's own process stays free of torch, SciPy and their thread pools until "
    "it has forked its children (a fork after OpenBLAS or OpenMP threads started can hang the child)",
}


def _function_level_imports(path: Path) -> list[str]:
    """The project modules imported inside a function of ``path`` (TYPE_CHECKING blocks are not functions)."""
    found = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if in_function and isinstance(child, ast.ImportFrom) and (child.module or "").startswith("vid2sim"):
                found.append(child.module)
            elif in_function and isinstance(child, ast.Import):
                found.extend(a.name for a in child.names if a.name.startswith("vid2sim"))
            visit(child, inner)

    visit(ast.parse(path.read_text()), False)
    return found


def test_project_imports_sit_at_the_top_of_their_module():
    """An import inside a function hides a cycle or an upward arrow from the tests above; the few that break a
    cycle, and the fuzz campaign's, are listed with their reason."""
    hidden = [f"{m} imports {target} inside a function" for m, p in _modules().items()
              for target in _function_level_imports(p)
              if (m, target) not in NESTED and not any(m.startswith(k) for k in NESTED_PACKAGES)]
    assert not hidden, hidden


#: the longest function and module the layout allows (issue #49: "functions that fit on a screen")
MAX_FUNCTION_LINES = 100
MAX_MODULE_LINES = 1000


def test_functions_and_modules_stay_short():
    """No function in src/ is longer than MAX_FUNCTION_LINES lines (decorators excluded, docstring included), no
    module longer than MAX_MODULE_LINES: a long one is split into named steps or modules."""
    long_functions, long_modules = [], []
    for module, path in _modules().items():
        text = path.read_text()
        if text.count("\n") > MAX_MODULE_LINES:
            long_modules.append(f"{module}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long_functions.append(f"{module}.{node.name} ({path.name}:{node.lineno}): {lines} lines")
    assert not long_functions, "functions too long:\n" + "\n".join(long_functions)
    assert not long_modules, "modules too long:\n" + "\n".join(long_modules)
