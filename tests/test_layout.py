"""The package layout keeps the promises docs/architecture.md makes: folders of a readable size, package
interfaces instead of private imports, parameter objects instead of long argument lists, and one event loop
(no thread) driving a study in ``workers/``."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ardcore", "workers", "service")


def sources():
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            yield p, ast.parse(p.read_text(), filename=str(p))


def test_no_folder_holds_more_than_twelve_modules():
    for pkg in PACKAGES:
        for folder in [ROOT / pkg, *[d for d in (ROOT / pkg).rglob("*") if d.is_dir()]]:
            modules = [p for p in folder.glob("*.py") if p.name != "__init__.py"]
            assert len(modules) <= 12, f"{folder.relative_to(ROOT)} holds {len(modules)} modules"


def test_no_private_name_crosses_a_module_and_no_reexport_is_silenced():
    crossing = []
    for p, tree in sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                crossing += [f"{p.relative_to(ROOT)}:{node.lineno} {a.name}" for a in node.names
                             if a.name.startswith("_") and not a.name.startswith("__")]
        assert "noqa: F401" not in p.read_text(), p
    assert not crossing


def test_no_function_takes_more_than_seven_parameters_outside_numba_kernels():
    long = []
    tests = [(p, ast.parse(p.read_text())) for p in sorted((ROOT / "tests").rglob("*.py"))]
    for p, tree in [*sources(), *tests]:
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if any("jit" in ast.unparse(d) for d in node.decorator_list):
                continue
            a = node.args
            names = [x.arg for x in a.posonlyargs + a.args]
            n = len(names) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)
            n -= bool(names and names[0] in ("self", "cls"))
            if n > 7:
                long.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({n})")
    assert not long


def test_the_study_driver_starts_no_thread():
    """workers/ drives a study as one loop over Dask events (:func:`workers.graph.run_study`): no thread,
    thread pool or executor of its own."""
    for p, tree in sources():
        if p.relative_to(ROOT).parts[0] != "workers":
            continue
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert not any(m.split(".")[0] == "threading" or "ThreadPool" in m or "Executor" in m
                               for m in mods), f"{p.relative_to(ROOT)}:{node.lineno}"


def _module(p: Path) -> str:
    parts = list(p.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_runs_in_a_circle():
    """docs/architecture.md: no import runs back up, none runs in a circle (imports inside functions count:
    a circle hidden in a function is still one)."""
    graph: dict[str, set] = {}
    for p, tree in sources():
        me = _module(p)
        pkg = me.split(".") if p.name == "__init__.py" else me.split(".")[:-1]
        deps = graph.setdefault(me, set())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = ".".join(pkg[:len(pkg) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    base = (node.module or "").removeprefix("ardflow.")
                names = [f"{base}.{a.name}" for a in node.names] + [base]
                deps.update(n for n in names if n.split(".")[0] in PACKAGES)
    modules = set(graph)
    graph = {m: {d for d in ds if d in modules and d != m} for m, ds in graph.items()}
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for d in graph[m]:
            if state.get(d) == 1:
                raise AssertionError("import circle: " + " -> ".join(path[path.index(d):] + [d]))
            if d not in state:
                visit(d, path + [d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
