"""The package's import graph (README, "Architecture"): no cycles, imports pointing down the layers,
the core never importing a front end, and internal imports at module top.

Every ``import`` of a ``guidewire3d`` module counts, also those inside function bodies (a lazy
import hides a cycle; it does not remove it).
"""
from __future__ import annotations

import ast
import importlib
from pathlib import Path


CORE = Path(__file__).resolve().parents[1] / "core"

# Lowest first; a module may import its own layer and the layers below it, never one above. A module's
# layer is that of its package (``cta.vessels3d`` is in ``cta``); the base is the package's top level.
LAYERS: dict[str, tuple[str, ...]] = {
    "base": ("guidewire3d", "errors", "geometry", "vesseltree", "io", "metrics", "assets", "methods", "kernels"),
    # the stages of DESIGN.md, in the order of the flow
    "CTA": ("cta",),
    "2D X-ray": ("xray",),
    "registration": ("registration",),
    "motion": ("motion",),
    "reconstruction": ("reconstruction",),
    "engine": ("live",),
    "simulation": ("phantom",),
    "application": ("app",),
    "front ends": ("app.cli", "viewer"),
}
FRONT_ENDS = {"app.cli", "viewer"}
# The command line imports a command's modules when the command runs, so that `--help` and every
# other command start without loading all the stages (measured: ~1.5 s of imports).
LAZY_ALLOWED = {"app.cli"}


def _unit(module: str) -> str:
    """The entry of LAYERS a module belongs to: itself if named there, else its package."""
    return module if module in LAYER_NAMES else module.split(".")[0]


def _modules() -> dict[str, Path]:
    mods = {}
    for p in sorted(CORE.rglob("*.py")):
        parts = p.relative_to(CORE).with_suffix("").parts
        name = ".".join(parts[:-1]) if parts[-1] == "__init__" else ".".join(parts)
        mods[name or "guidewire3d"] = p
    return mods


def _imports(mods: dict[str, Path]) -> list[tuple[str, str, bool, int]]:
    """(importer, imported, at module top, line) for every internal import."""
    def short(full: str) -> str | None:
        if full == "guidewire3d":
            return "guidewire3d"
        if full.startswith("guidewire3d."):
            rest = full[len("guidewire3d."):]
            return rest if rest in mods else None
        return None

    edges = []
    for name, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        top_level = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            for full in targets:
                dst = short(full)
                if dst is not None and dst != name:
                    edges.append((name, dst, id(node) in top_level, node.lineno))
    return edges


LAYER_NAMES = {m for ms in LAYERS.values() for m in ms}
MODULES = _modules()
EDGES = _imports(MODULES)
LAYER_OF = {m: i for i, (_, ms) in enumerate(LAYERS.items()) for m in ms}
LAYER_OF.update({m: LAYER_OF[_unit(m)] for m in MODULES if _unit(m) in LAYER_OF})


def test_every_module_has_a_layer():
    assert sorted(set(MODULES) - set(LAYER_OF)) == [], "add new packages to LAYERS (and the README's table)"
    assert sorted(LAYER_NAMES - set(MODULES)) == [], "LAYERS names a module or package that does not exist"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every cycle met by a depth-first walk of ``graph`` (each as the modules along it)."""
    state: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                found.append(stack[stack.index(n):] + [n])
            elif n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle():
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for a, b, _, _ in EDGES:
        graph[a].add(b)
    assert sum(len(v) for v in graph.values()) > 50          # the graph was read (the package has >100 imports)
    assert [" -> ".join(c) for c in _cycles(graph)] == []


def test_imports_point_down_the_layers():
    names = list(LAYERS)
    upward = [f"{a} ({names[LAYER_OF[a]]}) imports {b} ({names[LAYER_OF[b]]}), line {line}"
              for a, b, _, line in EDGES if LAYER_OF[b] > LAYER_OF[a]]
    assert upward == []


def test_the_core_never_imports_a_front_end():
    bad = [f"{a} imports {b}, line {line}" for a, b, _, line in EDGES
           if _unit(b) in FRONT_ENDS and _unit(a) not in FRONT_ENDS]
    assert bad == []


def test_internal_imports_are_at_module_top():
    lazy = [f"{a} imports {b} in a function, line {line}" for a, b, top, line in EDGES
            if not top and a not in LAZY_ALLOWED]
    assert lazy == []


def test_the_plugin_uses_the_package_api_only():
    """The Slicer module imports guidewire3d's public modules, never a private name."""
    plugin = Path(__file__).resolve().parents[1] / "plugin"
    private = []
    for p in plugin.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("guidewire3d"):
                private += [f"{p.name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert private == []


# Folders whose name was a module's before the folders existed: their public names stay importable from
# the folder (``from guidewire3d.motion import track_poses``, the API evaluation scripts call).
REEXPORTING = ("registration", "motion", "reconstruction", "live", "phantom")


def _public_names(path: Path) -> list[str]:
    names = []
    for node in ast.parse(path.read_text(), str(path)).body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            names += [t.id for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.append(node.target.id)
    return [n for n in names if not n.startswith("_")]


def test_folders_reexport_their_public_names():
    missing = []
    for pkg in REEXPORTING:
        package = importlib.import_module(f"guidewire3d.{pkg}")
        submodules = {m.split(".")[-1] for m in MODULES if m.startswith(pkg + ".")}
        for name in sorted(m for m in MODULES if m.startswith(pkg + ".")):
            module = importlib.import_module(f"guidewire3d.{name}")
            missing += [f"guidewire3d.{pkg}.{n} (from {name})" for n in _public_names(MODULES[name])
                        if n not in submodules and getattr(package, n, None) is not getattr(module, n)]
    assert missing == []
    from guidewire3d.live import Session
    from guidewire3d.motion import track_poses
    from guidewire3d.phantom import simulate
    from guidewire3d.reconstruction import reconstruct_wire
    from guidewire3d.registration import register
    assert all(callable(f) for f in (Session, track_poses, simulate, reconstruct_wire, register))
