"""The layering rules of the house (docs/design/ARCHITECTURE.md, "Dependency direction") and one typed error
tree per layer, read from the source (ast: the rules import no module; the last test checks the reading
against Python).

- Imports point inward: ``model/`` imports none of ``drivers``, ``service``, ``api``; ``drivers/`` none of
  ``service``, ``api``. Inside the service the contracts sit below everything (``service.contracts``, the
  value types the packages hand each other, imports only itself, ``service.errors``, the model, numpy and the
  standard library); the store imports no engine (``core``, ``shell``, ``host``), no ``serve`` and no
  estimator (``estimate``); ``serve`` (and the service protocol the API reads, ``service.serve.interface``)
  no ``store``, no engine; ``acquire``, ``estimate``, ``identify`` none of the wiring (the engine, the tools,
  ``api``). The engine itself points inward: ``service.core`` (pure) imports none of
  ``service.shell``/``service.host`` and no asyncio, thread or database driver; ``service.shell`` none of
  ``service.host``. Only the engine and the tools wire the packages (and the API) together. The API reads the
  service through ``serve`` and ``contracts`` only (and ``errors``, its settings' types and the log context:
  leaves that import nothing deeper, checked too). Every import counts, also one inside a function or under
  ``TYPE_CHECKING``. No module-level import cycle; no class in ``service/`` over 400 lines.
- No import cycles between packages (``service.<package>``, ``model``, ``drivers``, ``api``, ``benchmarks``).
- The laboratory stays out of the product (issue 39): nothing under ``model``, ``drivers``, ``service``,
  ``api`` imports ``benchmarks`` (which may import anything), and the running product (core, shell,
  host, estimate, identify, store, serve, acquire, api) imports nothing of the simulator or the plant
  (``simulator``, ``model.plant``, ``model.plantmech``): those serve the demo, the simulate command, the
  tests and the benchmarks. The wheel built from the tree holds no benchmark, study or diagnostic module
  (``test_the_wheel_ships_no_laboratory``).
- Every exception class defined in a layer derives from that layer's root: ``model.errors.ModelError``,
  ``drivers.errors.DriverError``, ``service.errors.ServiceError``, ``api.errors.ApiError``.
"""

from __future__ import annotations

import ast
import builtins
import itertools
import re
import shutil
import subprocess
import sys
import zipfile
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("model", "drivers", "service", "simulator", "api")
SCANNED = (*LAYERS, "benchmarks")  # the benchmarks are read too: the rules below name what they may not be


@dataclass
class Module:
    name: str
    path: Path
    imports: set[str] = field(default_factory=set)  # every imported module (a from-import's names included)
    names: dict[str, tuple[str, str]] = field(default_factory=dict)  # local name -> (module, name) imported
    classes: dict[str, list[ast.expr]] = field(default_factory=dict)  # class name -> its bases


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _absolute(mod: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.name.split(".")
    is_pkg = mod.path.name == "__init__.py"
    base = base[: len(base) - node.level + (1 if is_pkg else 0)]
    return ".".join([*base, node.module] if node.module else base)


def _parse(path: Path) -> Module:
    mod = Module(_module_name(path), path)
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mod.imports.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(mod, node)
            mod.imports.add(source)
            for a in node.names:
                mod.imports.add(f"{source}.{a.name}")
                mod.names[a.asname or a.name] = (source, a.name)
        elif isinstance(node, ast.ClassDef):
            mod.classes[node.name] = node.bases
    return mod


@cache
def modules() -> dict[str, Module]:
    found = {}
    for layer in SCANNED:
        for path in sorted((ROOT / layer).rglob("*.py")):
            if "migrations" not in path.parts:
                mod = _parse(path)
                found[mod.name] = mod
    return found


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def _offending(importer: str, forbidden: tuple[str, ...]) -> list[str]:
    return sorted(
        f"{m.name} imports {i}"
        for m in modules().values()
        if _under(m.name, importer)
        for i in m.imports
        if any(_under(i, f) for f in forbidden)
    )


_SERVICE_PACKAGES = tuple(
    f"service.{p.stem}"
    for p in sorted((ROOT / "service").iterdir())
    if (p.is_dir() and (p / "__init__.py").exists()) or p.suffix == ".py"
    if p.stem not in ("__init__", "contracts", "errors")
)
_TOOLS = ("service.commands", "benchmarks", "simulator", "service.cli")
# the engine, in three packages (issue 39): the pure core, the asyncio shell, the host; with the tools and
# the api they are the wiring, which no lower package imports
_ENGINE = ("service.core", "service.shell", "service.host")
_RUNNING = (
    *_ENGINE,
    "service.estimate",
    "service.identify",
    "service.store",
    "service.serve",
    "service.acquire",
    "api",
)
_SIMULATOR = ("simulator", "model.plant", "model.plantmech")
_SHELL = (*_ENGINE, *_TOOLS, "api")
# leaves of the service that are no layer: the configuration, its MQTT section and the log context; what they
# import is checked below, so a layer that imports them reaches nothing deeper through them
_LEAVES = ("service.settings", "service.mqttsettings", "service.logctx")
_API_READS = ("service.serve", "service.contracts", *_LEAVES)  # and service.errors

RULES = [
    # the pure core: no shell, no host, no tool; no event loop, no thread, no database driver
    (
        "service.core",
        ("service.shell", "service.host", *_TOOLS, "asyncio", "threading", "concurrent", "sqlalchemy"),
    ),
    ("service.shell", ("service.host", *_TOOLS)),
    ("service.host", ("service.commands", "benchmarks", "service.cli")),
    ("model", ("drivers", "service", "simulator", "api")),
    ("drivers", ("service", "simulator", "api")),
    ("service", ("api",)),  # issue 28: the REST outlet is found by name (service.serve.outlet.OUTLETS)
    ("service.errors", ("service.", "model", "drivers", "api")),
    ("service.contracts", (*_SERVICE_PACKAGES, "drivers", "api")),  # below every other service package
    ("service.store", (*_SHELL, "service.serve", "service.estimate")),
    ("service.serve", (*_SHELL, "service.store")),
    ("service.serve.interface", (*_SHELL, "service.store")),
    ("service.identify", (*_SHELL, "service.store", "service.serve")),
    ("service.estimate", (*_SHELL, "service.store", "service.serve")),
    ("service.acquire", (*_SHELL, "service.store")),
    ("api", tuple(p for p in _SERVICE_PACKAGES if p not in _API_READS)),  # serve, contracts: nothing deeper
    ("service.settings", tuple(p for p in _SERVICE_PACKAGES if p not in ("service.defaults", *_LEAVES))),
    ("service.mqttsettings", _SERVICE_PACKAGES),
    ("service.logctx", _SERVICE_PACKAGES),
    # issue 39: the laboratory out of the product; the running product imports no simulator and no plant
    *((layer, ("benchmarks",)) for layer in LAYERS),
    *((running, _SIMULATOR) for running in _RUNNING),
]


@pytest.mark.parametrize(("importer", "forbidden"), RULES, ids=[r[0] for r in RULES])
def test_imports_point_inward(importer: str, forbidden: tuple[str, ...]) -> None:
    assert any(_under(m, importer) for m in modules()), f"no module {importer}"
    assert _offending(importer, forbidden) == []


def _import_graph(names: set[str]) -> dict[str, list[str]]:
    return {n: sorted(i for i in modules()[n].imports if i in names and i != n) for n in sorted(names)}


def _cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """The import cycles of ``graph`` (module -> modules it imports): its strongly connected components of
    more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(graph[root]))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(graph[w])))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def test_no_module_import_cycles() -> None:
    """No circle of imports between the product's modules (every import counts, also under
    ``TYPE_CHECKING``): e.g. the core's parts and its serving strategies (issue 39)."""
    assert _cycles(_import_graph(set(modules()))) == []


def test_the_module_cycle_check_sees_a_cycle() -> None:
    graph = {"a": ["b"], "b": ["c"], "c": ["a", "d"], "d": [], "e": ["a"]}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": ["b"], "b": []}) == []


MAX_CLASS_LINES = 400  # issue 39: no god class in the service


def _class_lines(root: str) -> dict[str, int]:
    """Every class under ``root`` (nested ones too) -> its length in lines, read with ast."""
    out = {}
    for m in modules().values():
        if _under(m.name, root):
            tree = ast.parse(m.path.read_text(encoding="utf-8"), str(m.path))
            for node in ast.walk(tree):
                if isinstance(node, ast.ClassDef) and node.end_lineno is not None:
                    out[f"{m.name}.{node.name}"] = node.end_lineno - node.lineno + 1
    return out


def test_no_class_in_the_service_over_400_lines() -> None:
    lines = _class_lines("service")
    assert "service.core.machine.ServiceCore" in lines
    big = {name: n for name, n in lines.items() if n > MAX_CLASS_LINES}
    assert big == {}, big


def test_the_rules_see_a_violation() -> None:
    """The checker itself: a known import is found (so an empty list above means something)."""
    assert "service.store.reads imports service.store.errors.DatabaseBusyError" in _offending(
        "service.store", ("service.store.errors",)
    )
    # the benchmarks are read, and they do import the simulator (what the product may not)
    assert "benchmarks.compensation_run imports simulator.plantsamples" in _offending(
        "benchmarks", ("simulator",)
    )


_LAB_NAME = re.compile(r"bench|diag\d*|stud(y|ies)", re.IGNORECASE)


@pytest.mark.slow
def test_the_wheel_ships_no_laboratory(tmp_path: Path) -> None:
    """The wheel built from the tree holds the product's packages only (issue 39): no ``benchmarks``, and no
    bench, study or diagnostic module inside them (none named so, none named as a study of
    ``benchmarks/studies``). Built from a copy: a build in the tree would leave ``build/`` behind."""
    src = tmp_path / "src"
    junk = shutil.ignore_patterns(".git", ".*cache*", "__pycache__", "*.egg-info", "build", "dist", "tests")
    shutil.copytree(ROOT, src, ignore=junk)
    out = tmp_path / "wheel"
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out)]
    built = subprocess.run([*cmd, "."], cwd=src, capture_output=True, text=True, timeout=240)
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = out.glob("*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names if ".dist-info/" not in n} == set(LAYERS)
    studies = {p.stem for p in (ROOT / "benchmarks" / "studies").glob("*.py")} - {"__init__"}
    modules = [Path(n) for n in names if n.endswith(".py")]
    assert len(modules) > 100  # the product is there
    lab = [str(m) for m in modules if m.stem in studies or any(_LAB_NAME.search(part) for part in m.parts)]
    assert lab == []


def test_the_contracts_are_types_only() -> None:
    """``service.contracts`` imports the standard library, numpy, the model and the service's own errors:
    no SQLAlchemy, pydantic, asyncio server or driver (what crosses packages carries no I/O)."""
    allowed = ("numpy", "model", "service.contracts", "service.errors", "_typeshed")
    strays = sorted(
        f"{m.name} imports {i}"
        for m in modules().values()
        if _under(m.name, "service.contracts")
        for i in m.imports
        if i.split(".")[0] not in sys.stdlib_module_names and not any(_under(i, a) for a in allowed)
    )
    assert strays == []


def package_of(module: str) -> str:
    """The package a module belongs to in the cycle check: ``service.<package>`` (a top-level module of the
    service counts as its own package), else its layer (``model``, ``drivers``, ``api``)."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "service" and len(parts) > 1 else parts[0]


def package_graph() -> dict[str, dict[str, str]]:
    """package -> {imported package: one module import that makes the edge}, from the parsed imports."""
    graph: dict[str, dict[str, str]] = {}
    for m in modules().values():
        src = package_of(m.name)
        for i in sorted(m.imports):
            target = i
            while target and target not in modules():  # a from-import's name: its module
                target = target.rpartition(".")[0]
            dst = package_of(target) if target else ""
            if dst and dst != src:
                graph.setdefault(src, {}).setdefault(dst, f"{m.name} imports {i}")
    return graph


def find_cycle(graph: dict[str, dict[str, str]]) -> list[str]:
    """One cycle of ``graph`` as its path (``[a, b, ..., a]``); [] when there is none (depth-first)."""
    state: dict[str, int] = {}  # 1 on the path, 2 done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == 1:
                return [*path[path.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


def test_no_import_cycle_between_packages() -> None:
    graph = package_graph()
    cycle = find_cycle(graph)
    edges = [graph[a][b] for a, b in itertools.pairwise(cycle)]
    assert cycle == [], "import cycle " + " -> ".join(cycle) + ":\n  " + "\n  ".join(edges)


def test_the_cycle_check_sees_a_cycle() -> None:
    """The checker itself: a known package edge is read, and a cycle in a graph is found with its path."""
    assert package_graph()["service.store"]["service.contracts"]
    assert find_cycle({"a": {"b": ""}, "b": {"c": ""}, "c": {"b": ""}}) == ["b", "c", "b"]
    assert find_cycle({"a": {"b": ""}, "b": {"c": ""}}) == []


def _resolve(module: str, name: str) -> tuple[str, str]:
    """(defining module, class name) of ``name`` as seen in ``module``; ("builtins", name) for a builtin."""
    mod = modules().get(module)
    if mod is None:
        return (module, name)
    if name in mod.classes:
        return (module, name)
    if name in mod.names:
        source, original = mod.names[name]
        if source in modules():
            return _resolve(source, original)
        return (source, original)
    return ("builtins", name)


def _bases(module: str, name: str) -> list[tuple[str, str]]:
    out = []
    for b in modules()[module].classes[name]:
        if isinstance(b, ast.Name):
            out.append(_resolve(module, b.id))
        elif isinstance(b, ast.Attribute):
            out.append((ast.unparse(b.value), b.attr))
    return out


@cache
def _ancestors(cls: tuple[str, str]) -> frozenset[tuple[str, str]]:
    module, name = cls
    if module not in modules() or name not in modules()[module].classes:
        return frozenset()
    found: set[tuple[str, str]] = set()
    for base in _bases(module, name):
        found |= {base, *_ancestors(base)}
    return frozenset(found)


def _is_exception(cls: tuple[str, str]) -> bool:
    for module, name in {cls, *_ancestors(cls)}:
        builtin = getattr(builtins, name, None) if module == "builtins" else None
        if isinstance(builtin, type) and issubclass(builtin, BaseException):
            return True
    return False


ROOTS = {
    "model": ("model.errors", "ModelError"),
    "drivers": ("drivers.errors", "DriverError"),
    "service": ("service.errors", "ServiceError"),
    "simulator": ("simulator.errors", "SimulatorError"),
    "api": ("api.errors", "ApiError"),
}


def _exceptions(layer: str) -> list[tuple[str, str]]:
    return [
        (m.name, c)
        for m in modules().values()
        if _under(m.name, layer)
        for c in m.classes
        if _is_exception((m.name, c))
    ]


@pytest.mark.parametrize("layer", LAYERS)
def test_every_exception_of_a_layer_derives_from_its_root(layer: str) -> None:
    root = ROOTS[layer]
    found = _exceptions(layer)
    assert root in found and len(found) > 1
    strays = [f"{m}.{c}" for m, c in found if (m, c) != root and root not in _ancestors((m, c))]
    assert strays == [], f"not derived from {'.'.join(root)}"


def test_the_roots_are_what_the_code_raises() -> None:
    """The static reading agrees with Python's own for a few classes across the trees."""
    from api.errors import ApiError
    from drivers.errors import DriverError
    from drivers.sim.faults import FaultSpecError
    from model.errors import ModelError
    from model.identify import InsufficientDataError
    from model.rom_cache import CacheReadError
    from service.contracts.errors import NotReadyError
    from service.errors import ServiceError
    from service.store.errors import DatabaseBusyError, RecordError, RecordRejectedError

    assert issubclass(InsufficientDataError, ModelError) and issubclass(InsufficientDataError, ValueError)
    assert issubclass(CacheReadError, ModelError) and issubclass(CacheReadError, OSError)
    assert issubclass(FaultSpecError, DriverError)
    assert issubclass(DatabaseBusyError, ServiceError) and not issubclass(DatabaseBusyError, NotReadyError)
    assert issubclass(RecordRejectedError, RecordError)
    assert not issubclass(ServiceError, ApiError)
    for cls in (InsufficientDataError, CacheReadError, FaultSpecError, DatabaseBusyError):
        layer = cls.__module__.split(".")[0]
        assert (ROOTS[layer][0], ROOTS[layer][1]) in _ancestors((cls.__module__, cls.__name__))
