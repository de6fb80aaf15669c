"""The edge install stays light: ``pip install egosurg`` on a node (JetPack 6, Python 3.10) resolves
what the agent, recorder, console, keys and session tools import, and none of the heavy libraries
of the workstation (a CUDA-13 torch on aarch64 alone is gigabytes of wheels a node cannot use).

The base dependencies in pyproject.toml are the edge; the workstation's libraries live in extras.
The installed distribution's metadata is checked too, with everything it pulls in, because that
is what pip resolves on a node. This file runs under Python 3.10 as well (make edge-check)."""

from __future__ import annotations

import importlib.metadata
import re
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):  # noqa: UP036 - this file runs on JetPack 6's Python 3.10 too
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]

# What a node must never install; each of these lives in an extra of the workstation.
HEAVY = frozenset(
    {"torch", "open3d", "numba", "scipy", "matplotlib", "av", "tqdm", "ray", "viser", "gsplat"}
)
# What the edge's modules import (capture_agent/, protocol/); tomli only before Python 3.11.
EDGE = frozenset(
    {
        "numpy",
        "pyzmq",
        "opencv-contrib-python-headless",
        "h5py",
        "xxhash",
        "cryptography",
        "ptpython",
        "tomli-w",
        "tomli",
    }
)


def _name(requirement: str) -> str:
    """The normalised project name of a requirement string (PEP 503: lower case, '-')."""
    match = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
    assert match, f"not a requirement: {requirement!r}"
    return re.sub(r"[-_.]+", "-", match.group(1)).lower()


def _project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _base_requirements(distribution: str) -> list[str]:
    """The installed distribution's requirements outside any extra (what plain pip resolves)."""
    return [
        r for r in importlib.metadata.requires(distribution) or [] if "extra ==" not in r.lower()
    ]


def test_the_base_dependencies_are_the_edge_and_hold_no_heavy_package():
    names = {_name(r) for r in _project()["dependencies"]}
    assert names == EDGE, f"the edge install's requirements changed: {sorted(names ^ EDGE)}"
    assert not names & HEAVY


def test_the_workstation_extras_still_hold_every_heavy_package():
    """make installs the workstation, dev and bench extras: the full product, as before."""
    extras = _project()["optional-dependencies"]
    make_installs = {_name(r) for e in ("workstation", "dev", "bench") for r in extras[e]}
    assert HEAVY <= make_installs, f"missing from make's install: {sorted(HEAVY - make_installs)}"


def test_the_edge_admits_jetpack_6_python():
    assert _project()["requires-python"].startswith(">=3.10")


def test_the_installed_edge_pulls_in_no_heavy_package():
    """Everything the installed egosurg needs without extras, followed through the requirements
    of what is installed here (environment markers counted as true: an over-estimate)."""
    try:
        seen = {_name(r) for r in _base_requirements("egosurg")}
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("egosurg is not installed (pip install -e .)")
    assert not seen & HEAVY, f"egosurg's own requirements hold {sorted(seen & HEAVY)}"
    todo = sorted(seen)
    while todo:
        name = todo.pop()
        try:
            needs = {_name(r) for r in _base_requirements(name)}
        except importlib.metadata.PackageNotFoundError:
            continue  # not installed here (a marker for another Python): nothing to follow
        assert not needs & HEAVY, f"{name} pulls in {sorted(needs & HEAVY)}"
        todo.extend(sorted(needs - seen))
        seen |= needs


def test_a_workstation_command_on_a_node_names_the_extra_to_install(monkeypatch, capsys):
    """On a node, `egosurg calibrate` cannot import open3d: one line that says what to install."""
    from protocol import cli

    def missing(name: str) -> None:
        raise ModuleNotFoundError("No module named 'open3d'", name="open3d")

    monkeypatch.setattr(cli.importlib, "import_module", missing)
    assert cli.main(["calibrate", "--help"]) == 2
    err = capsys.readouterr().err
    assert "open3d" in err and "pip install 'egosurg[workstation]'" in err, err
