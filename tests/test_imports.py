"""The kernels package's import graph: the modules stand in layers (the tree record, the
stages, the conveniences and builders above them), so none imports, even inside a
function, a module that imports it back; and the kernels never import the Mitsuba
plugin above them (``hlbvh`` itself, ``hlbvh.accel``, ...)."""

import ast
from pathlib import Path

KERNELS = Path(__file__).resolve().parent.parent / "kernels"
PACKAGE = "hlbvh.kernels"


def imports_of(path: Path) -> set[str]:
    """Every module ``path`` imports, absolute names, wherever the import stands (top
    level, inside a function or a method)."""
    module = f"{PACKAGE}.{path.stem}"
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.rsplit(".", node.level)[0]
                name = f"{base}.{node.module}" if node.module else base
            else:
                name = node.module
            # `from . import x` and `from .pkg import x` may name modules too.
            found |= {name} | {f"{name}.{alias.name}" for alias in node.names}
    return found


def kernel_graph(folder: Path = KERNELS) -> dict[str, set[str]]:
    """Each kernels module's imports among the kernels modules."""
    modules = {f"{PACKAGE}.{p.stem}": p for p in folder.glob("*.py")}
    return {name: imports_of(path) & set(modules) - {name} for name, path in modules.items()}


def cycle_in(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` as the list of its modules (first repeated last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node):
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test01_kernels_import_graph_has_no_cycle():
    graph = kernel_graph()
    assert len(graph) > 20, "the kernels package was not found"
    cycle = cycle_in(graph)
    assert cycle is None, "import cycle among the kernels: " + " -> ".join(cycle)


def test02_cycle_finder_finds_an_import_inside_a_function(tmp_path):
    """The check sees an import made inside a function (the way the circle hid)."""
    (tmp_path / "a.py").write_text("from .b import f\n")
    (tmp_path / "b.py").write_text("def f():\n    from .a import g\n    return g\n")
    (tmp_path / "c.py").write_text("import drjit\n")
    assert cycle_in(kernel_graph(tmp_path)) in (
        [f"{PACKAGE}.a", f"{PACKAGE}.b", f"{PACKAGE}.a"],
        [f"{PACKAGE}.b", f"{PACKAGE}.a", f"{PACKAGE}.b"])


def test03_kernels_never_import_the_plugin():
    for path in sorted(KERNELS.glob("*.py")):
        plugin = {name for name in imports_of(path)
                  if (name == "hlbvh" or name.startswith("hlbvh."))
                  and not name.startswith(PACKAGE + ".") and name != PACKAGE}
        assert not plugin, f"kernels/{path.name} imports the plugin: {sorted(plugin)}"
