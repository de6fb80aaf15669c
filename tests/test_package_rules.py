"""The architecture as a test (docs/architecture.md), checked on the source: the five packages the
design fixes stay the top level, which package may import which, which wing of capture_agent/,
protocol/ and calibration/ and which reconstructor stage may import which, no import cycle
anywhere in the five packages (imports only a type checker reads included), the edge imports no
heavy library, and every module the ``egosurg`` dispatcher names imports and has its function."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from protocol.cli import COMMANDS

REPO = Path(__file__).resolve().parents[1]
PACKAGES = {"protocol", "sim", "capture_agent", "calibration", "reconstructor"}
ALLOWED = {
    "protocol": set(),
    "sim": {"protocol"},
    "capture_agent": {"protocol", "sim"},
    "calibration": {"protocol"},
    "reconstructor": {"protocol"},
}
# Inside reconstructor/: each part (a subpackage or a top-level module) and the other parts it
# may import. The stages run data -> depth -> splats -> refine; pipeline and config tie them
# together; evaluation judges the result and only the commands (cli) reach into it.
_SHARED = {"errors", "plugins"}
RECONSTRUCTOR_PARTS: dict[str, set[str]] = {
    "errors": set(),
    "plugins": set(),
    "raster": {"errors"},  # the GPU backend's one-line refusal is a ReconstructError
    "data": {"errors"},
    "depth": {"data"} | _SHARED,
    "splats": {"data", "raster"} | _SHARED,
    "refine": {"data", "splats", "raster"} | _SHARED,
    "config": {"data", "depth", "splats", "refine", "raster"} | _SHARED,
    "pipeline": {"data", "depth", "splats", "refine", "raster", "config"} | _SHARED,
    # evaluation also scores the case's warm start (Table 3B's warm row)
    "evaluation": {"data", "depth", "splats", "refine", "raster", "config", "pipeline", "case"}
    | _SHARED,
    "case": {"data", "depth", "splats", "refine", "raster", "config", "pipeline"} | _SHARED,
    # reviewing a case (docs/replay.md): reads the case index and renders its models
    "replay": {"case", "data", "splats", "raster", "config"} | _SHARED,
    # finding people (docs/replay.md): a case's stored points or a session's stereo depth
    "people": {"case", "data", "depth", "config", "pipeline", "replay"} | _SHARED,
    # the case report (docs/report.md): the review outputs and the pictures replay makes
    "report": {"replay", "case", "data", "splats", "raster", "config"} | _SHARED,
    "cli": {"data", "depth", "splats", "refine", "raster", "config", "pipeline", "evaluation"}
    | {"case"}
    | _SHARED,
    "__init__": {"splats"},  # the CPU's denormal setting, before any worker thread starts
}


# Inside capture_agent/, protocol/ and calibration/: each wing (a folder, or "top" for the
# package's own modules) and the other wings it may import. The top holds what every wing shares
# (configs, security, errors, the camera model), so it imports no wing; the wings never import
# each other but as listed.
WINGS: dict[str, dict[str, set[str]]] = {
    "capture_agent": {
        "top": set(),  # config, security, the daemon loop, the control server
        "sources": {"top"},  # the camera seam and its backends
        "agent": {"top", "sources"},  # the edge daemon drives a source
        "recorder": {"top"},
        "operator": {"top"},  # talks to the recorder over its socket, never imports it
    },
    "protocol": {
        "top": set(),  # errors, the camera model, images, the TOML idiom, the command helper
        "session": {"top", "sealing"},  # a sealed session's key block and payloads
        # rig.toml's image and buffer limits are the wire's (MAX_FRAME_BYTES, wire/frame_limits)
        "formats": {"top", "wire"},
        "wire": {"top", "session"},  # an agent's status reply names the session's camera info
        "sealing": {"top"},  # keys and AEAD only: the session will import it, never the reverse
    },
    "calibration": {
        "top": set(),  # errors, and the observations that detection hands to the solver
        "detect": {"top"},
        "solve": {"top"},
        "report": {"top"},  # judges and draws a solved calibration it is given
        "cli": {"top", "detect", "solve", "report"},  # the command runs the three in order
    },
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _all_modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in sorted(PACKAGES) for p in (REPO / pkg).rglob("*.py")}


def _imported(path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of the five packages that ``path`` imports, at the top or inside a function
    (a lazy import still closes a cycle at run time); ``from a import b`` counts as ``a.b``
    where that is a module, else as ``a`` (a package's own ``__init__`` runs before its
    submodules, so the package a submodule sits in is not an edge). Imports under
    ``if TYPE_CHECKING:`` count too: they never run, but a module that names another's types
    depends on it, and a circle of them is a circle a reader must follow."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    return _imported_by(name, package, path.read_text(), modules)


def _imported_by(name: str, package: str, source: str, modules: dict[str, Path]) -> set[str]:
    found: set[str] = set()
    tree = ast.parse(source)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            subs = {f"{base}.{a.name}" for a in node.names}
            found |= subs & modules.keys()
            if not subs <= modules.keys():  # a name defined in base itself
                found.add(base)
    return {m for m in found if m in modules and m != name}


def _graph() -> dict[str, set[str]]:
    modules = _all_modules()
    return {name: _imported(path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_packages_import_only_what_the_design_allows():
    for name, imports in _graph().items():
        pkg = name.split(".")[0]
        bad = {m.split(".")[0] for m in imports} - ALLOWED[pkg] - {pkg}
        assert not bad, f"{name} imports {sorted(bad)}"


def test_the_import_graph_of_the_five_packages_has_no_cycle():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles (move the shared piece so imports run one way): " + (
        "; ".join(" <-> ".join(c) for c in cycles)
    )


def test_the_cycle_finder_finds_a_cycle():
    """The rule above can fail: a three-module loop and a self-contained chain."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def _part(module: str) -> str:
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def test_each_reconstructor_stage_imports_only_the_stages_before_it():
    graph = _graph()
    seen = set()
    for name, imports in graph.items():
        if not name.startswith("reconstructor"):
            continue
        part = _part(name)
        seen.add(part)
        assert part in RECONSTRUCTOR_PARTS, (
            f"{name} is in a part of reconstructor/ the rules do not know: add {part!r} to "
            "RECONSTRUCTOR_PARTS here and to docs/architecture.md"
        )
        inner = {_part(m) for m in imports if m.startswith("reconstructor.")} - {part}
        bad = inner - RECONSTRUCTOR_PARTS[part]
        assert not bad, f"{name} imports reconstructor parts {sorted(bad)}"
    assert {"data", "depth", "splats", "refine", "evaluation", "pipeline"} <= seen


def test_nothing_outside_evaluation_imports_it_but_the_commands():
    for name, imports in _graph().items():
        if name.startswith("reconstructor.evaluation") or name == "reconstructor.cli":
            continue
        reached = sorted(m for m in imports if m.startswith("reconstructor.evaluation"))
        assert not reached, f"{name} imports {reached}: training must not depend on its judge"


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_module_the_dispatcher_names_imports_and_has_its_function(command):
    module_name, _, func_name = COMMANDS[command][0].partition(":")
    module = importlib.import_module(module_name)
    assert callable(getattr(module, func_name, None)), f"{module_name} has no {func_name}()"


# The edge (protocol/ and capture_agent/) runs on a Jetson node, installed without the
# reconstruction's libraries: none of its modules may import one. The one exception is the
# simulator's camera source, which is the simulator (it is never used on a node).
HEAVY = ("torch", "open3d", "numba", "scipy", "matplotlib", "av", "tqdm")
EDGE_EXCEPTIONS = {"capture_agent.sources.sim_source"}


def test_the_edge_imports_without_heavy_libraries():
    """protocol/__init__'s promise, checked for every module of protocol/ and capture_agent/."""
    edge = sorted(
        m
        for m in _all_modules()
        if m.split(".")[0] in ("protocol", "capture_agent") and m not in EDGE_EXCEPTIONS
    )
    snippet = (
        "import importlib, sys\n"
        f"for m in {edge!r}:\n"
        "    importlib.import_module(m)\n"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", snippet], capture_output=True, text=True, check=True, cwd=REPO
    )
    assert out.stdout.strip() == "", f"the edge's modules load {out.stdout.strip()}"


def _wing(module: str) -> str:
    parts = module.split(".")
    wings = WINGS[parts[0]]
    return parts[1] if len(parts) > 1 and parts[1] in wings else "top"  # "cli": a module


@pytest.mark.parametrize("package", sorted(WINGS))
def test_each_wing_imports_only_the_wings_the_design_allows(package):
    rules = WINGS[package]
    for name, imports in _graph().items():
        if name.split(".")[0] != package:
            continue
        wing = _wing(name)
        inner = {_wing(m) for m in imports if m.split(".")[0] == package} - {wing}
        bad = inner - rules[wing]
        assert not bad, f"{name} (wing {wing!r}) imports the wings {sorted(bad)}"


@pytest.mark.parametrize("package", sorted(WINGS))
def test_every_folder_of_a_winged_package_is_a_wing_the_rules_know(package):
    folders = {d.name for d in (REPO / package).iterdir() if (d / "__init__.py").is_file()}
    unknown = folders - set(WINGS[package]) - {"cli"}
    assert not unknown, (
        f"{package}/ has folders the rules do not know: {sorted(unknown)}; add each to WINGS "
        "here (with what it may import) and to docs/architecture.md"
    )


def test_the_five_packages_the_design_fixes_stay_the_top_level():
    top = {d.name for d in REPO.iterdir() if (d / "__init__.py").is_file()} - {"tests"}
    assert top == PACKAGES, f"top-level packages {sorted(top)}, the design fixes {sorted(PACKAGES)}"
    include = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "packages"
    ]["find"]["include"]
    assert {i.rstrip("*") for i in include} == PACKAGES


def test_the_rules_see_imports_only_a_type_checker_reads():
    """A circle of ``if TYPE_CHECKING:`` imports is a circle too: the finder must see it."""
    source = (
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from protocol.camera import X\n"
    )
    found = _imported_by("protocol.probe", "protocol", source, _all_modules())
    assert found == {"protocol.camera"}


def test_no_module_imports_another_modules_private_names():
    """A leading underscore says "mine": a module that needs a helper of another asks for it to be
    made public (or moved to where both can use it) rather than reaching in. A private module
    (``calibration/detect/_reference.py``, the slow twins) may be imported whole by its package."""
    modules = _all_modules()
    reached = []
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
                continue
            if node.module.split(".")[0] not in PACKAGES:
                continue
            for alias in node.names:
                private = alias.name.startswith("_") and not alias.name.startswith("__")
                if private and f"{node.module}.{alias.name}" not in modules:
                    reached.append(f"{name} imports {node.module}.{alias.name}")
    assert not reached, "; ".join(reached)
