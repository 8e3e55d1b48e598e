"""The package installs under one namespace (`fednav.*`) while the repository keeps top-level folders."""

from __future__ import annotations

import ast
import importlib
import importlib.metadata as md
import importlib.resources
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PACKAGE_DIR: dict[str, str] = PYPROJECT["tool"]["setuptools"]["package-dir"]
TOPS = {folder: name for name, folder in PACKAGE_DIR.items()}


def _folders_with_init() -> set[str]:
    found = set()
    for folder, name in TOPS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((name, *rel)))
    return found


def test_every_package_folder_is_listed_in_pyproject():
    listed = set(PYPROJECT["tool"]["setuptools"]["packages"])
    assert _folders_with_init() == listed


def test_installed_distribution_has_one_top_level_name():
    top = md.distribution("fednav").read_text("top_level.txt")
    assert top is not None and top.split() == ["fednav"]


def test_console_scripts_and_blueprint_entry_points_load():
    scripts = [e for e in md.entry_points(group="console_scripts") if e.value.startswith("fednav.")]
    assert {e.name for e in scripts} >= {"fednav-service", "fednav-sim", "fednav-view", "fednav-inspect"}
    for entry in [*scripts, *md.entry_points(group="fednav.blueprints")]:
        assert callable(entry.load()), entry


def test_no_source_imports_a_bare_top_level_package():
    bare = []
    for path in [p for folder in (*TOPS, "tests", "benchmarks") for p in (ROOT / folder).rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            bare += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in TOPS]
    assert not bare, "import through the fednav namespace:\n" + "\n".join(bare)


def test_package_data_is_reachable_through_the_namespace():
    scenarios = importlib.resources.files("fednav.simulators") / "scenarios"
    assert any(p.name == "demo_aircraft.toml" for p in scenarios.iterdir())
    configs = importlib.resources.files("fednav.service") / "configs"
    assert (configs / "example.toml").is_file()
    assert importlib.import_module("fednav.service").__name__ == "fednav.service"
