"""The layers point one way: fsw (the flight software) is a leaf; hil (the simulated world) and ground
(the ground segment) build on fsw and not on each other — the ground reads only the scenario files of
hil, as the description of a simulated mission; bench (benchmarks and campaigns) may use all three.
Every import statement of every module is checked, at any depth in the module (inside functions
too)."""
import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fsw", "hil", "ground", "bench")
#: what each layer may import from the project's packages (modules given by their dotted prefix)
ALLOWED = {
    "fsw": ("fsw",),
    "hil": ("fsw", "hil"),
    "ground": ("fsw", "ground", "hil.scenario"),
    "bench": ("fsw", "hil", "ground", "bench"),
}


def imported_modules(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, absolute dotted name) of every project module the file imports."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    here = list(path.relative_to(ROOT).with_suffix("").parts)
    if here[-1] == "__init__":
        here = here[:-1]
    else:
        here = here[:-1]  # the package the module is in
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = here[:len(here) - node.level + 1] if node.level > 1 else here
                name = ".".join(base + ([node.module] if node.module else []))
                out += [(node.lineno, name + "." + a.name if not node.module else name) for a in node.names]
            else:  # a name imported from a package may be a module of it: `from hil import scenario`
                out += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
    return [(line, name) for line, name in out if name.split(".")[0] in PACKAGES]


def violations(package: str) -> list[str]:
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, name in imported_modules(path, package):
            if not any(name == ok or name.startswith(ok + ".") for ok in ALLOWED[package]):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    return bad


@pytest.mark.parametrize("package", PACKAGES)
def test_no_layer_imports_upward(package):
    assert violations(package) == []


def test_the_check_sees_an_upward_import_at_any_depth(tmp_path, monkeypatch):
    """The checker itself: an import of hil inside a function of an fsw module, and a relative import
    that climbs out of the package, are both seen."""
    pkg = tmp_path / "fsw" / "estimation"
    pkg.mkdir(parents=True)
    (pkg / "bad.py").write_text("def f():\n    from hil import sim\n    return sim\n")
    (pkg / "worse.py").write_text("from ...ground import decode\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    found = violations("fsw")
    assert any("bad.py:2 imports hil" in v for v in found)
    assert any("worse.py:1 imports ground" in v for v in found)
