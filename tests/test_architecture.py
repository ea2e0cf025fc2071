"""The layout's mechanical rules (docs/architecture.md), checked by reading the code's AST.

- no module imports a private (``_name``) from another module;
- no import cycles among graphcal's modules, counting imports inside functions;
- no function (or method) over ``MAX_FUNCTION_LINES`` lines;
- one installed top-level package;
- nothing outside ``graphcal/simulation/`` imports the simulator except ``graphcal/commands/``;
- the layers contract (docs/architecture.md, ``LAYERS``): a package imports only packages of lower
  layers, never one of its own layer or above (imports inside functions counted).

Run this file as a script to print every violation (``python tests/test_architecture.py``).
"""
from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "graphcal"
MAX_FUNCTION_LINES = 150
# may import graphcal.simulation (besides the simulator itself): the command layer and the test helpers
SIMULATION_USERS = ("graphcal.commands", "graphcal.simulation", "graphcal.testing")
#: the library's layers, lowest first (docs/architecture.md): a package may import a package of a
#: lower layer only. ``simulation`` and ``testing`` sit beside the library, below ``commands``.
LAYERS = (
    ("", "geometry", "errors", "stats", "progress"),
    ("models",),
    ("io",),
    ("factors", "solvers"),
    ("clouds",),
    ("calibration", "legs", "locomotion", "batch"),
    ("diagnosis", "planning", "logs"),
    ("report",),
    ("simulation",),
    ("testing",),
    ("commands",),
    ("cli",),
    ("__main__",),
)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def resolve(mod: str, node: ast.ImportFrom, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = mod.split(".") if is_package else mod.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(mod: str, path: Path, known: dict[str, Path]):
    """(line, imported module, imported name or None) for every import in a module, at any depth."""
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            target = resolve(mod, node, path.name == "__init__.py")
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in known:
                    yield node.lineno, sub, None
                else:
                    yield node.lineno, target, alias.name


def import_graph() -> dict[str, set[str]]:
    known = modules()
    graph: dict[str, set[str]] = {m: set() for m in known}
    for mod, path in known.items():
        for _, target, _ in imports(mod, path, known):
            if target in known and target != mod:
                graph[mod].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(root: str) -> None:
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter[0]
                    counter[0] += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    component.append(top)
                    if top == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def private_imports() -> list[str]:
    known = modules()
    bad = []
    for mod, path in known.items():
        for line, target, name in imports(mod, path, known):
            if not target.startswith("graphcal"):
                continue
            parts = target.split(".") + ([name] if name else [])
            if any(p.startswith("_") and not p.startswith("__") for p in parts):
                bad.append(f"{path.relative_to(ROOT)}:{line}: {target}{'.' + name if name else ''}")
    return bad


def long_functions() -> list[str]:
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.name} ({length} lines)")
    return bad


def simulator_imports() -> list[str]:
    known = modules()
    bad = []
    for mod, path in known.items():
        if mod.startswith(SIMULATION_USERS):
            continue
        for line, target, _ in imports(mod, path, known):
            if target.startswith("graphcal.simulation"):
                bad.append(f"{path.relative_to(ROOT)}:{line}: {target}")
    return bad


def package_of(mod: str) -> str:
    """``graphcal.calibration.graph`` -> ``calibration``; ``graphcal.cli`` -> ``cli``; ``graphcal`` -> ``""``."""
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer_index() -> dict[str, int]:
    return {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}


def upward_imports(graph: dict[str, set[str]] | None = None) -> list[str]:
    """Every import of a package of the same or a higher layer (``module -> module``), and every
    package the layers table does not name."""
    graph = import_graph() if graph is None else graph
    rank = layer_index()
    bad = []
    for mod in sorted(graph):
        a = package_of(mod)
        if a not in rank:
            bad.append(f"{mod}: package {a!r} is in no layer of LAYERS")
            continue
        for target in sorted(graph[mod]):
            b = package_of(target)
            if b == a or b not in rank:
                continue
            if rank[b] >= rank[a]:
                where = "beside" if rank[b] == rank[a] else "above"
                bad.append(f"{mod} -> {target} ({b} is {where} {a})")
    return bad


def installed_top_level() -> list[str]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    include = config["tool"]["setuptools"]["packages"]["find"]["include"]
    return sorted({pattern.split(".")[0].rstrip("*") for pattern in include})


def test_no_private_imports_across_modules():
    assert private_imports() == []


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_no_function_over_the_limit():
    assert long_functions() == []


def test_one_top_level_package():
    assert installed_top_level() == ["graphcal"]
    assert not (ROOT / "factors").exists()


def test_library_never_imports_the_simulator():
    assert simulator_imports() == []


def test_layers_contract():
    assert upward_imports() == []


def test_the_layers_check_sees_an_upward_and_a_sideways_import():
    graph = {"graphcal.calibration.graph": {"graphcal.report.write", "graphcal.io.files"},
             "graphcal.legs.identify": {"graphcal.locomotion.ekf"},
             "graphcal.report.write": {"graphcal.calibration.graph"}, "graphcal.io.files": set(),
             "graphcal.locomotion.ekf": set(), "graphcal.wizard.x": set()}
    assert upward_imports(graph) == [
        "graphcal.calibration.graph -> graphcal.report.write (report is above calibration)",
        "graphcal.legs.identify -> graphcal.locomotion.ekf (locomotion is beside legs)",
        "graphcal.wizard.x: package 'wizard' is in no layer of LAYERS",
    ]


def test_importing_graphcal_sets_nothing_in_tqdm_and_its_bar_starts_no_thread():
    import subprocess

    code = ("import io, threading, tqdm; before = tqdm.tqdm.monitor_interval; import graphcal, graphcal.cli; "
            "from graphcal.progress import ProgressBar; bar = ProgressBar(total=2, file=io.StringIO()); bar.update(); "
            "print(before, tqdm.tqdm.monitor_interval, threading.active_count())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == out[1] != "0"  # tqdm's own default (10) untouched
    assert out[2] == "1"  # no monitor thread beside the main one


def test_the_scan_sees_a_cycle_and_a_private_import():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


if __name__ == "__main__":
    report = {
        "private imports": private_imports(),
        "cycles": [" -> ".join(c) for c in cycles(import_graph())],
        "long functions": long_functions(),
        "simulator imports": simulator_imports(),
        "layers (upward or sideways imports)": upward_imports(),
        "top-level packages": installed_top_level(),
    }
    for title, rows in report.items():
        print(f"## {title}: {len(rows)}")
        for row in rows:
            print("  ", row)
    sys.exit(0)
