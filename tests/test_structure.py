"""
One-way module structure: the command line sits on top, nothing imports it, the algorithm's update engine sits below
the algorithm, the networks need no Stable-Baselines3, and the package's imports have no circle.
"""

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Torch-only modules: the networks and the numerics helpers they use (autocast, precision), none of them importing SB3
NETWORKS = ("latent", "critics", "actor", "fused_rollout", "convolutions", "gaussian", "numerics")
# What DSSLAC delegates its updates to: below it, never importing it back
UPDATE_ENGINE = ("bursts", "gradient_step", "numerics", "lagrange", "optim")


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
    assert "sb3_dsslac.cli" in graph["sb3_dsslac.__main__"]
    assert "sb3_dsslac.runs" in graph["sb3_dsslac.plotting"] and "sb3_dsslac.envs" in graph["sb3_dsslac.hpo"]


def test_only_main_imports_the_command_line() -> None:
    importers = [module for module, imports in package_graph("sb3_dsslac").items() if "sb3_dsslac.cli" in imports]
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


def reachable(graph: dict[str, set[str]], module: str) -> set[str]:
    """Every module of the graph that ``module`` imports, directly or through others."""
    found: set[str] = set()
    stack = [module]
    while stack:
        for name in graph[stack.pop()]:
            if name in graph and name not in found:
                found.add(name)
                stack.append(name)
    return found


def test_the_update_engine_sits_below_the_algorithm() -> None:
    graph = package_graph("sb3_dsslac")
    for name in UPDATE_ENGINE:
        assert "sb3_dsslac.dsslac" not in reachable(graph, f"sb3_dsslac.{name}"), name


def test_the_networks_need_no_stable_baselines() -> None:
    graph = package_graph("sb3_dsslac")
    networks = {f"sb3_dsslac.{name}" for name in NETWORKS}
    for module in networks:
        assert reachable(graph, module) <= networks, module
        path = REPO / "sb3_dsslac" / f"{module.split('.')[-1]}.py"
        assert not {name.split(".")[0] for name in imported_modules(path)} & {"stable_baselines3", "sb3_contrib"}, module
