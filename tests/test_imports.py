"""The import graph points upstream only (STYLE.md section 1).

Layers, lowest first; a module may import its own layer and lower ones:

    [errors, units, description, schema] < io < segment < model < fit < features
        < diagnose < discrepancy < store < report < cli

A subpackage is its layer; ``ident/__init__.py`` may import anything below ``cli``
and only ``cli`` may import the top-level package.  ``pipelines/``, ``notebooks/``
and ``benchmarks/`` use the public API only (no name starting with ``_``).  No
``import *`` anywhere, no global seeding (``np.random.seed``) in ``ident/``.

The checks parse every file with :mod:`ast` (imports inside functions count too)
and are themselves tested on small synthetic trees, so that they can fail.
"""

from __future__ import annotations

import ast
import json
from dataclasses import dataclass
from pathlib import Path

LAYERS: tuple[tuple[str, ...], ...] = (
    ("errors", "units", "description", "schema"),
    ("io",), ("segment",), ("model",), ("fit",), ("features",), ("diagnose",),
    ("discrepancy",), ("store",), ("report",), ("cli",),
)
LAYER_OF: dict[str, int] = {name: i for i, names in enumerate(LAYERS) for name in names}
#: the package's ``__init__``: above everything but cli
ROOT_LAYER = LAYER_OF["cli"] - 0.5
PUBLIC_API_DIRS = ("pipelines", "notebooks", "benchmarks")


@dataclass(frozen=True)
class Import:
    """One import statement's target, resolved to a dotted module name."""

    file: Path
    line: int
    target: str
    names: tuple[str, ...]  # imported names for ``from X import a, b``; () for ``import X``


def module_name(path: Path, src_root: Path) -> str:
    """``ident/model/laws.py`` -> ``ident.model.laws``; packages drop ``__init__``."""
    parts = list(path.relative_to(src_root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def parse_source(path: Path) -> ast.Module:
    """Parse a ``.py`` file, or the code cells of an ``.ipynb`` (magics dropped)."""
    if path.suffix == ".ipynb":
        nb = json.loads(path.read_text(encoding="utf-8"))
        cells = ["".join(c["source"]) if isinstance(c["source"], list) else c["source"]
                 for c in nb.get("cells", []) if c.get("cell_type") == "code"]
        # magics become blank lines, so that line numbers count the code cells' lines
        code = "\n".join("" if ln.lstrip().startswith(("%", "!")) else ln
                          for cell in cells for ln in cell.splitlines())
        return ast.parse(code, filename=str(path))
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def imports_of(path: Path, src_root: Path | None) -> list[Import]:
    """Every import in ``path`` with relative imports resolved against ``src_root``."""
    tree = parse_source(path)
    out: list[Import] = []
    if src_root is not None:
        mod = module_name(path, src_root)
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend(Import(path, node.lineno, a.name, ()) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if src_root is None:
                    raise ValueError(f"{path}:{node.lineno}: relative import outside a package")
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = tuple(a.name for a in node.names)
            # ``from pkg import sub`` imports the submodule pkg.sub when there is one
            for name in names:
                sub = f"{target}.{name}"
                if src_root is not None and _is_module(sub, src_root):
                    out.append(Import(path, node.lineno, sub, ()))
                else:
                    out.append(Import(path, node.lineno, target, (name,)))
    return out


def _is_module(dotted: str, src_root: Path) -> bool:
    p = src_root.joinpath(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def layer(dotted: str) -> float | None:
    """Layer of an ``ident`` module; None for a module with no layer assigned."""
    parts = dotted.split(".")
    if len(parts) == 1:
        return ROOT_LAYER
    return LAYER_OF.get(parts[1])


def layer_violations(src_root: Path, package: str = "ident") -> list[str]:
    """Imports inside ``src_root/package`` that point downstream, or into no layer."""
    problems: list[str] = []
    for path in sorted((src_root / package).rglob("*.py")):
        me = module_name(path, src_root)
        mine = layer(me)
        if mine is None:
            problems.append(f"{path}: module {me} has no layer; add its top-level name to "
                            f"LAYERS in tests/test_imports.py")
            continue
        for imp in imports_of(path, src_root):
            if imp.target != package and not imp.target.startswith(package + "."):
                continue
            theirs = layer(imp.target)
            if theirs is None:
                problems.append(f"{path}:{imp.line}: imports {imp.target}, which has no layer")
            elif theirs > mine:
                problems.append(f"{path}:{imp.line}: {me} imports {imp.target}, which is "
                                f"downstream of it")
    return problems


def star_imports(paths: list[Path]) -> list[str]:
    """``from X import *`` statements in ``paths``."""
    return [f"{p}:{node.lineno}: from {'.' * node.level}{node.module or ''} import *"
            for p in paths for node in ast.walk(parse_source(p))
            if isinstance(node, ast.ImportFrom) and any(a.name == "*" for a in node.names)]


def private_uses(path: Path, package: str = "ident") -> list[str]:
    """Uses of ``_private`` names of ``package`` (imports and attribute access)."""
    tree = parse_source(path)
    problems: list[str] = []
    bound: set[str] = set()   # local names bound to ident modules or objects

    def private(name: str) -> bool:
        return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == package or a.name.startswith(package + "."):
                    if any(private(p) for p in a.name.split(".")):
                        problems.append(f"{path}:{node.lineno}: import {a.name}")
                    bound.add((a.asname or a.name).split(".")[0])
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            if node.module == package or node.module.startswith(package + "."):
                if any(private(p) for p in node.module.split(".")):
                    problems.append(f"{path}:{node.lineno}: from {node.module} import ...")
                for a in node.names:
                    if private(a.name):
                        problems.append(f"{path}:{node.lineno}: from {node.module} import "
                                        f"{a.name}")
                    bound.add(a.asname or a.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and private(node.attr):
            root = node.value
            while isinstance(root, ast.Attribute):
                root = root.value
            if isinstance(root, ast.Name) and root.id in bound:
                problems.append(f"{path}:{node.lineno}: {ast.unparse(node)}")
    return problems


def global_seeding(path: Path) -> list[str]:
    """Calls that seed a global generator: ``np.random.seed``, ``random.seed``."""
    problems = []
    for node in ast.walk(parse_source(path)):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr == "seed":
            owner = node.func.value
            if (isinstance(owner, ast.Attribute) and owner.attr == "random") or \
                    (isinstance(owner, ast.Name) and owner.id == "random"):
                problems.append(f"{path}:{node.lineno}: {ast.unparse(node)}")
        if isinstance(node, ast.ImportFrom) and node.module in ("numpy.random", "random") \
                and any(a.name == "seed" for a in node.names):
            problems.append(f"{path}:{node.lineno}: from {node.module} import seed")
    return problems


def _files(root: Path, dirs: tuple[str, ...], suffixes=(".py", ".ipynb")) -> list[Path]:
    out = []
    for d in dirs:
        base = root / d
        if base.is_dir():
            out.extend(p for p in sorted(base.rglob("*")) if p.suffix in suffixes
                       and ".ipynb_checkpoints" not in p.parts)
    return out


# --- the repository -------------------------------------------------------------------------

def test_every_ident_module_has_a_layer_and_imports_upstream_only(repo_root):
    problems = layer_violations(repo_root)
    assert not problems, "\n".join(problems)


def test_no_star_imports_anywhere(repo_root):
    files = _files(repo_root, ("ident", "tests", *PUBLIC_API_DIRS))
    assert any(f.name == "laws.py" for f in files)  # the walk sees the package
    problems = star_imports(files)
    assert not problems, "\n".join(problems)


def test_pipelines_notebooks_benchmarks_use_public_api_only(repo_root):
    problems = [p for f in _files(repo_root, PUBLIC_API_DIRS) for p in private_uses(f)]
    assert not problems, "\n".join(problems)


def test_no_global_seeding_in_ident(repo_root):
    problems = [p for f in _files(repo_root, ("ident",), (".py",)) for p in global_seeding(f)]
    assert not problems, "\n".join(problems)


# --- the checks can fail --------------------------------------------------------------------

def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return tmp_path


def test_layer_check_catches_downstream_and_unassigned(tmp_path):
    root = _tree(tmp_path, {
        "ident/__init__.py": "from .model import laws\n",
        "ident/errors.py": "",
        "ident/model/__init__.py": "",
        "ident/model/laws.py": "from ..errors import X\nfrom . import other\n",
        "ident/model/other.py": "def f():\n    from ..fit import solver\n",   # downstream
        "ident/fit/__init__.py": "",
        "ident/fit/solver.py": "import ident.model.laws\nfrom ident.model import laws\n",
        "ident/io/__init__.py": "import ident\n",                            # root from io
        "ident/cli/__init__.py": "import ident\nfrom ident.fit import solver\n",
        "ident/magic.py": "",                                                # no layer
    })
    problems = layer_violations(root)
    assert len(problems) == 3, problems
    assert any("ident.model.other imports ident.fit.solver" in p for p in problems)
    assert any("ident.io imports ident, which is downstream" in p for p in problems)
    assert any("module ident.magic has no layer" in p for p in problems)


def test_relative_imports_resolve(tmp_path):
    root = _tree(tmp_path, {
        "ident/__init__.py": "", "ident/model/__init__.py": "",
        "ident/model/sub/__init__.py": "from ...errors import E\nfrom .. import laws\n",
        "ident/model/laws.py": "from .sub import thing\n",
        "ident/errors.py": "",
    })
    got = {(i.target, i.names) for i in imports_of(root / "ident/model/sub/__init__.py", root)}
    assert got == {("ident.errors", ("E",)), ("ident.model.laws", ())}
    got = {(i.target, i.names) for i in imports_of(root / "ident/model/laws.py", root)}
    assert got == {("ident.model.sub", ("thing",))}


def test_private_and_star_and_seed_checks_catch(tmp_path):
    root = _tree(tmp_path, {
        "pipelines/run.py": ("import ident.model._core\nfrom ident.model.laws import _contact\n"
                             "from ident import load_mill as lm\nimport ident.model.laws as L\n"
                             "L._contact_torque(1)\nlm._cache\nfrom ident.io import *\n"
                             "ident.__version__\n"),
        "ident/x.py": ("import numpy as np\nimport random\nnp.random.seed(0)\nrandom.seed(1)\n"
                       "rng = np.random.default_rng(0)\n"),
    })
    nb = {"cells": [{"cell_type": "code", "source": ["%matplotlib inline\n",
                                                     "from ident.model.laws import _x\n"]},
                    {"cell_type": "markdown", "source": "import ident._nope"}],
          "metadata": {}, "nbformat": 4, "nbformat_minor": 5}
    (root / "notebooks").mkdir()
    (root / "notebooks/n.ipynb").write_text(json.dumps(nb))
    run = private_uses(root / "pipelines/run.py")
    assert len(run) == 4, run
    assert private_uses(root / "notebooks/n.ipynb") == [
        f"{root / 'notebooks/n.ipynb'}:2: from ident.model.laws import _x"]
    assert len(star_imports([root / "pipelines/run.py"])) == 1
    assert len(global_seeding(root / "ident/x.py")) == 2
