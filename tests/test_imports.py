"""The import graph of the packages: no cycle (lazy imports inside functions count), and no
module importing another module's private name (what is shared is public)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pixloc", "pipeline", "workflows")


def _modules():
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            yield (".".join(parts[:-1]) if parts[-1] == "__init__" else ".".join(parts)), path


def _imports(name: str, path: Path):
    """(module imported, names taken from it) of every import in the file, at any depth."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, []
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")
                parent = parent[:len(parent) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            yield base, [alias.name for alias in node.names]


def _graph():
    modules = dict(_modules())
    graph = {m: set() for m in modules}
    private = []
    for name, path in modules.items():
        for target, names in _imports(name, path):
            for n in names:  # 'from package import module' imports a module
                if f"{target}.{n}" in modules:
                    graph[name].add(f"{target}.{n}")
            if target in modules and target != name:
                graph[name].add(target)
                private += [f"{name} imports {target}.{n}" for n in names
                            if n.startswith("_") and not n.startswith("__") and f"{target}.{n}" not in modules]
    return graph, private


def test_no_module_imports_a_private_name_of_another():
    """In the packages and in the tests: what is shared is public."""
    _, private = _graph()
    modules = dict(_modules())
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for target, names in _imports("tests", path):
            if target in modules:
                private += [f"{path.relative_to(ROOT)} imports {target}.{n}" for n in names
                            if n.startswith("_") and not n.startswith("__")]
    assert not private, "\n".join(private)


def test_the_import_graph_has_no_cycle():
    graph, _ = _graph()
    # a package's __init__ re-exporting its modules is not a cycle of code: leave those edges out
    edges = {m: {t for t in ts if not (t.startswith(m + ".") and (ROOT / m.replace(".", "/")).is_dir())}
             for m, ts in graph.items()}
    state, cycles = {}, []

    def visit(m, stack):
        state[m] = 1
        for t in sorted(edges.get(m, ())):
            if state.get(t) == 1:
                cycles.append(" -> ".join(stack[stack.index(t):] + [t]))
            elif t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    assert not cycles, "\n".join(cycles)
