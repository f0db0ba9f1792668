"""Facts about the code's structure read from the import graph: the library never imports the
learners, no module imports itself back through others, and PPO and PQN import no other learner."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).parents[1]
PACKAGES = ("snac_jax", "agents")


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def _imports(path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules `path` imports anywhere in its body (function-level imports included)."""
    found = set()
    package = _module_name(path) if path.name == "__init__.py" else _module_name(path).rpartition(".")[0]
    tree = ast.parse(path.read_text())
    typing_only = {
        id(inner)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for inner in ast.walk(node)
    }  # annotations only: nothing is imported at run time
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        else:
            continue
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name:
                found.add(name)
    return found - {_module_name(path)}


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, modules) for name, path in modules.items()}


def test_the_library_never_imports_the_learners():
    offenders = {
        m: sorted(i for i in deps if i.split(".")[0] == "agents")
        for m, deps in _graph().items()
        if m.split(".")[0] == "snac_jax"
    }
    assert not {m: d for m, d in offenders.items() if d}


def test_no_import_circles():
    graph = _graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(node):  # Tarjan's strongly connected components
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for dep in graph[node]:
            if dep not in index:
                visit(dep)
                low[node] = min(low[node], low[dep])
            elif dep in on_stack:
                low[node] = min(low[node], index[dep])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in graph:
        if node not in index:
            visit(node)
    # A package's __init__ that re-exports its submodules is not a circle of logic.
    cycles = [c for c in cycles if not all(m == c[0] or m.startswith(c[0] + ".") for m in c)]
    assert not cycles


LEARNER_MODULES = {
    "agents.learners.ppo",
    "agents.learners.pqn",
    "agents.learners.dqn",
    "agents.learners.drqn",
    "agents.learners.drqn_her",
    "agents.learners.rainbow",
    "agents.learners.sac",
    "agents.common.offpolicy",
    "agents.research.ppo_privileged",
    "agents.research.drqn_aux",
    "agents.research.pqn_aux",
    "agents.research.pqn_belief",
}


def test_ppo_and_pqn_fork_alone():
    """agents/learners/ppo.py and agents/learners/pqn.py import no other learner (only the library
    modules: networks, targets, inputs, config): the variants build on them in their own files, so
    a copy of either file runs without them."""
    graph = _graph()
    for name in ("agents.learners.ppo", "agents.learners.pqn"):
        assert not graph[name] & (LEARNER_MODULES - {name}), name
