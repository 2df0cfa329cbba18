"""The code's boundaries, checked on its text: a plug-in's name is written in its registry only, the
map store's keys in ``pipeline/store`` only, the environment read in the command line and
``pipeline.runtime`` only."""

import ast
import re
from pathlib import Path

from pipeline.descriptors import DESCRIPTORS
from pipeline.localization.priors import PRIORS
from pipeline.localization.retrieval import RETRIEVERS
from pipeline.mapping.readers.sources import SOURCES

ROOT = Path(__file__).resolve().parents[1]
CODE = sorted(p for folder in ("pipeline", "workflows", "pixloc") for p in (ROOT / folder).rglob("*.py"))
REGISTRIES = {"pipeline/localization/priors.py": PRIORS, "pipeline/localization/retrieval.py": RETRIEVERS,
              "pipeline/descriptors.py": DESCRIPTORS, "pipeline/mapping/readers/sources.py": SOURCES}
# where a value names a registry entry: keyword arguments, parameters, dict keys, compared names and
# attributes, and variables of these names (any case, plural too)
ENTRY_WORDS = {"prior", "method", "kind", "descriptor", "retrieval", "query_kind", "source"}
# calls whose first argument is an entry's name
ENTRY_CALLS = {"MapSource", "load_queries", "posed_images", "entry"}


def _word(name: str) -> bool:
    name = name.lower().rstrip("s")
    return name in ENTRY_WORDS or any(name.endswith("_" + w) for w in ENTRY_WORDS)


def _named(node) -> bool:
    """An expression that holds an entry's name: ``prior``, ``job.prior``, ``record["kind"]``."""
    if isinstance(node, ast.Name):
        return _word(node.id)
    if isinstance(node, ast.Attribute):
        return _word(node.attr)
    if isinstance(node, ast.Subscript):
        key = node.slice
        return isinstance(key, ast.Constant) and isinstance(key.value, str) and _word(key.value)
    return False


def _strings(node):
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        yield node.value
    elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        for item in node.elts:
            yield from _strings(item)


def entry_names_used(path: Path, names) -> list:
    """(line, name) of each string that names an entry, in a place where it is used as one."""
    found = []

    def flag(node, values):
        found.extend((node.lineno, v) for v in values if v in names)
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.keyword) and node.arg and _word(node.arg):
            flag(node.value, _strings(node.value))
        elif isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and isinstance(key.value, str) and _word(key.value):
                    flag(value, _strings(value))
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(_named(side) for side in sides):
                for side in sides:
                    flag(side, _strings(side))
        elif isinstance(node, ast.Call) and node.args:
            func = node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
            if func in ENTRY_CALLS:
                flag(node.args[0], _strings(node.args[0]))
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args.args + node.args.kwonlyargs
            defaults = [None] * (len(node.args.args) - len(node.args.defaults)) + node.args.defaults \
                + node.args.kw_defaults
            for arg, default in zip(args, defaults):
                if default is not None and _word(arg.arg):
                    flag(default, _strings(default))
        elif isinstance(node, ast.Assign):
            if any(isinstance(t, ast.Name) and _word(t.id) for t in node.targets):
                flag(node.value, _strings(node.value))
    return found


def test_no_entry_name_outside_its_registry():
    """Before: prior, retrieval and source names were string-checked in three layers (``"hloc"`` in
    ``resolve_order``, ``("gem", "grid")`` in the build-map options ...). The command line, presets,
    planner and benchmarks now ask the registries; a new entry is one class."""
    names = {name for registry in REGISTRIES.values() for name in registry}
    assert {"top1", "sift", "global", "pairs", "gem", "grid", "colmap", "strecha", "list"} <= names
    assert entry_names_used(ROOT / "tests" / "test_boundaries.py", {"x"}) == []
    probe = ROOT / "tests" / "data_probe_boundaries.py"
    try:  # the check sees each kind of use
        probe.write_text('def f(prior="top1"):\n    if job.retrieval.method == "pairs" or r["kind"] in ("colmap",):\n'
                         '        MapSource("strecha", p)\n    return {"descriptor": "grid"}\n')
        assert sorted(v for _, v in entry_names_used(probe, names)) == ["colmap", "grid", "pairs", "strecha", "top1"]
    finally:
        probe.unlink()
    used = [f"{p.relative_to(ROOT)}:{line}: {name!r}" for p in CODE if str(p.relative_to(ROOT)) not in REGISTRIES
            for line, name in entry_names_used(p, names)]
    assert used == [], "\n".join(used)


STORE_KEY = re.compile(r"""["'](images/(name|path|camera|tags|cam_from_world|row_start|num_obs)|points/xyz|"""
                       r"""observations/|features/)|\.attrs\[|\.attrs\.get\(|open_store\(|\bread\((root|group)\b""")


def test_no_store_key_outside_the_store_package():
    """Before: the map build, the planner, the report and the benchmarks read and wrote raw zarr keys
    (27 times in 8 files). The store's readers and writers are in ``pipeline/store``."""
    used = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in CODE
            if not str(p.relative_to(ROOT)).startswith("pipeline/store/")
            for n, line in enumerate(p.read_text().splitlines(), 1) if STORE_KEY.search(line)]
    assert used == [], "\n".join(used)


ENVIRONMENT = re.compile(r"os\.environ|os\.getenv|getenv\(")
# the command line (its startup and the processes it starts) and the runtime module
MAY_READ_ENVIRONMENT = {"pipeline/runtime.py", "workflows/cli.py"}


def test_the_environment_is_read_by_the_command_line_and_the_runtime_module_only():
    """Before: the pixel limit and the storage options reached workers as environment variables
    (not those of an external scheduler), and ``pixloc/nets/unet.py`` read a test hook."""
    used = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in CODE
            if str(p.relative_to(ROOT)) not in MAY_READ_ENVIRONMENT
            for n, line in enumerate(p.read_text().splitlines(), 1) if ENVIRONMENT.search(line)]
    assert used == [], "\n".join(used)
