"""The architecture's dependency rules (DESIGN.md), checked on the source."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = {"protocol", "sim", "capture_agent", "calibration", "reconstructor"}
ALLOWED = {
    "protocol": set(),
    "sim": {"protocol"},
    "capture_agent": {"protocol", "sim"},
    "calibration": {"protocol"},
    "reconstructor": {"protocol"},
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names & PACKAGES


def test_packages_import_only_what_the_design_allows():
    for pkg, allowed in ALLOWED.items():
        for path in (REPO / pkg).rglob("*.py"):
            bad = _imports(path) - allowed - {pkg}
            assert not bad, f"{path.relative_to(REPO)} imports {sorted(bad)}"


def test_protocol_and_the_command_import_without_heavy_libraries():
    """The agent runs on a Jetson: protocol/ and the egosurg dispatcher stay light."""
    snippet = (
        "import sys, protocol.cli, protocol.zed_conf, protocol.camera, protocol.wand\n"
        "import capture_agent\n"
        "heavy = [m for m in ('torch', 'open3d', 'matplotlib', 'numba') if m in sys.modules]\n"
        "print(','.join(heavy))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", snippet], capture_output=True, text=True, check=True, cwd=REPO
    )
    assert out.stdout.strip() == ""
