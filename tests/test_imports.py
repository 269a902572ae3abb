"""The package's import graph: every module of the installed ``hlbvh`` (the plugin, the
kernels, the scenes, the comparison, each folder mapped as setup.py maps it, sub-packages
included) stands in layers, so none imports, even inside a function, a module that
imports it back; and the kernels never import the Mitsuba plugin above them (``hlbvh``
itself, ``hlbvh.accel``, ...)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: Each import name's folder, as setup.py maps the package.
ROOTS = {"hlbvh": ROOT / "plugin", "hlbvh.kernels": ROOT / "kernels",
         "hlbvh.scenes": ROOT / "scenes", "hlbvh.comparison": ROOT / "comparison"}


def modules_under(package: str, folder: Path) -> dict[str, Path]:
    """Every module of ``folder`` and its sub-packages by its import name (a package by
    its ``__init__.py``), ``package`` the folder's own import name."""
    found = {}
    for path in sorted(folder.rglob("*.py")):
        parts = list(path.relative_to(folder).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join([package, *parts])] = path
    return found


def package_modules(roots: dict[str, Path] = ROOTS) -> dict[str, Path]:
    """Every module of the package, each under the name it is imported by."""
    found = {}
    for package, folder in roots.items():
        found.update(modules_under(package, folder))
    return found


def _known(name: str, modules) -> str | None:
    """The module ``name`` is, or the innermost package of the package it is in (the
    one whose code runs), or None outside the package."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules) -> set[str]:
    """The modules of ``modules`` that module ``name`` (at ``path``) imports, wherever
    the import stands (top level, inside a function or a method): ``import a.b`` is
    ``a.b``; ``from a import b`` is the module ``a.b`` where there is one, else ``a``
    (the module that defines ``b``)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {_known(alias.name, modules) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                found.add(submodule if submodule in modules else _known(source, modules))
    return found - {None, name}


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Each module's imports among ``modules``."""
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


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


def test01_the_package_import_graph_has_no_cycle():
    modules = package_modules()
    for package in ROOTS:
        assert package in modules, f"{package} was not found"
    assert {"hlbvh.kernels.sah", "hlbvh.accel.scene_accel", "hlbvh.render.frame"} <= set(modules)
    cycle = cycle_in(import_graph(modules))
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def _write(folder: Path, files: dict[str, str]) -> dict[str, Path]:
    for relative, text in files.items():
        (folder / relative).parent.mkdir(parents=True, exist_ok=True)
        (folder / relative).write_text(text)
    return modules_under("pkg", folder)


def test02_cycle_finder_finds_an_import_inside_a_function(tmp_path):
    """The check sees an import made inside a function (the way the kernels' circle hid)."""
    modules = _write(tmp_path, {"__init__.py": "", "a.py": "from .b import f\n",
                                "b.py": "def f():\n    from .a import g\n    return g\n",
                                "c.py": "import drjit\n"})
    assert cycle_in(import_graph(modules)) in (["pkg.a", "pkg.b", "pkg.a"],
                                               ["pkg.b", "pkg.a", "pkg.b"])


def test03_relative_imports_resolve_in_packages_and_their_modules(tmp_path):
    """``from . import x`` in a package's ``__init__`` names the package's own module,
    ``from ..x import y`` in a sub-package's module its parent's module; a name that is
    no module is an edge to the module that defines it, absolute imports count too."""
    modules = _write(tmp_path, {
        "__init__.py": "",
        "arrays.py": "",
        "sah/__init__.py": "from . import planes\nfrom .lanes import build\n",
        "sah/lanes.py": "from ..arrays import Float\nfrom .planes import cost\n",
        "sah/planes.py": "def f():\n    import pkg.arrays\n",
        "top.py": "from pkg.sah import binned_sah\nfrom pkg import arrays, sah\n"})
    assert import_graph(modules) == {
        "pkg": set(), "pkg.arrays": set(),
        "pkg.sah": {"pkg.sah.planes", "pkg.sah.lanes"},
        "pkg.sah.lanes": {"pkg.arrays", "pkg.sah.planes"},
        "pkg.sah.planes": {"pkg.arrays"},
        "pkg.top": {"pkg.sah", "pkg.arrays"}}
    (tmp_path / "sah" / "planes.py").write_text("from . import build\n")
    cycle = cycle_in(import_graph(modules_under("pkg", tmp_path)))
    assert cycle is not None and {"pkg.sah", "pkg.sah.planes"} <= set(cycle)


def test04_kernels_never_import_the_plugin():
    modules = package_modules()
    graph = import_graph(modules)
    kernels = [name for name in modules if name.startswith("hlbvh.kernels")]
    assert len(kernels) > 20
    for name in kernels:
        plugin = {imported for imported in graph[name] if not imported.startswith("hlbvh.kernels")
                  and imported.split(".")[1:2] not in (["scenes"], ["comparison"])}
        assert not plugin, f"{modules[name].relative_to(ROOT)} imports the plugin: {sorted(plugin)}"
