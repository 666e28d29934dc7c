"""
The package's folders are its layers: a module imports only modules of its own folder or of the folders below it, the
networks need no Stable-Baselines3, the command line sits on top with nothing importing it, and the imports have no
circle.
"""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Bottom to top; "" is the package's own folder (the algorithm: dsslac, presets, version)
LAYERS = ("nn", "common", "engine", "", "app")
# Run as ``python -m``: they may import the application, and nothing imports them
ENTRY_POINTS = ("sb3_dsslac.__main__", "sb3_dsslac.zoo")


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports, at the top or inside a function (``from a import b`` counts as ``a`` and ``a.b``)."""
    package = module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else module_name(path)
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def package_graph(package: str) -> dict[str, set[str]]:
    """Module -> the modules of ``package`` (and of sb3_dsslac / safety_envs) it imports."""
    graph = {}
    for path in sorted((REPO / package).rglob("*.py")):
        graph[module_name(path)] = {
            name for name in imported_modules(path) if name.split(".")[0] in ("sb3_dsslac", "safety_envs")
        }
    return graph


def test_the_parser_sees_imports() -> None:
    graph = package_graph("sb3_dsslac")
    assert "sb3_dsslac.app.cli" in graph["sb3_dsslac.__main__"]
    assert "sb3_dsslac.app.runs" in graph["sb3_dsslac.app.plotting"]
    assert "sb3_dsslac.common.envs" in graph["sb3_dsslac.app.hpo"]


def test_only_main_imports_the_command_line() -> None:
    importers = [module for module, imports in package_graph("sb3_dsslac").items() if "sb3_dsslac.app.cli" in imports]
    assert importers == ["sb3_dsslac.__main__"]


def test_safety_envs_imports_nothing_of_sb3_dsslac() -> None:
    for module, imports in package_graph("safety_envs").items():
        assert not [name for name in imports if name.startswith("sb3_dsslac")], module


def test_no_import_circle() -> None:
    graph = package_graph("sb3_dsslac")
    edges = {module: {name for name in imports if name in graph and name != module} for module, imports in graph.items()}
    done: set[str] = set()

    def visit(module: str, path: list[str]) -> None:
        if module in path:
            raise AssertionError(f"import circle: {' -> '.join([*path[path.index(module) :], module])}")
        if module in done:
            return
        for name in sorted(edges[module]):
            visit(name, [*path, module])
        done.add(module)

    for module in sorted(edges):
        visit(module, [])


def layer(module: str) -> int:
    """The layer of a module of sb3_dsslac, from its folder."""
    parts = module.split(".")
    folder = parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else ""
    return LAYERS.index(folder)


def test_every_module_sits_in_a_layer_folder() -> None:
    folders = {path.parent.name for path in (REPO / "sb3_dsslac").rglob("*.py")}
    assert folders == {"sb3_dsslac", *[name for name in LAYERS if name]}


def test_layers_import_only_their_own_folder_and_those_below() -> None:
    graph = package_graph("sb3_dsslac")
    upward = [
        f"{module} -> {name}"
        for module, imports in graph.items()
        if module not in ENTRY_POINTS
        for name in imports
        if name.startswith("sb3_dsslac.") and name in graph and layer(name) > layer(module)
    ]
    assert upward == []


def test_the_package_front_imports_no_application() -> None:
    """``import sb3_dsslac`` (the public names) loads no command line, tuning or zoo code."""
    assert not [name for name in package_graph("sb3_dsslac")["sb3_dsslac"] if name.startswith("sb3_dsslac.app")]


@pytest.mark.parametrize("entry_point", ENTRY_POINTS)
def test_nothing_imports_an_entry_point(entry_point: str) -> None:
    assert not [module for module, imports in package_graph("sb3_dsslac").items() if entry_point in imports]


def test_the_layer_rule_sees_an_upward_import() -> None:
    assert layer("sb3_dsslac.nn.latent") < layer("sb3_dsslac.common.policies") < layer("sb3_dsslac.engine.bursts")
    assert layer("sb3_dsslac.engine.bursts") < layer("sb3_dsslac.dsslac") < layer("sb3_dsslac.app.cli")
    assert layer("sb3_dsslac.presets") == layer("sb3_dsslac.dsslac")


def test_the_networks_need_no_stable_baselines() -> None:
    for path in (REPO / "sb3_dsslac" / "nn").glob("*.py"):
        roots = {name.split(".")[0] for name in imported_modules(path)}
        assert not roots & {"stable_baselines3", "sb3_contrib", "gymnasium"}, path.name
