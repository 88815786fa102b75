"""The documentation: generated result tables match the committed JSON (a hand edit fails), every
relative link resolves inside the repository, and the README stays a short front door."""
import importlib.util
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
while not (ROOT / "pyproject.toml").is_file() and ROOT != ROOT.parent:   # tests/ or tests/<dir>/
    ROOT = ROOT.parent
DOCS = ROOT / "docs"
README = ROOT / "README.md"

spec = importlib.util.spec_from_file_location("docs_tables", DOCS / "tables.py")
tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tables)

LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def pages() -> list[Path]:
    return [README] + sorted(DOCS.rglob("*.md"))


def _docs_copy(tmp_path: Path) -> Path:
    copy = tmp_path / "docs"
    shutil.copytree(DOCS, copy, ignore=shutil.ignore_patterns("*.png", "__pycache__"))
    return copy


def test_committed_tables_match_their_json():
    assert tables.stale(DOCS) == []


def test_every_table_name_is_used_and_every_marker_known():
    used = set()
    for p in pages():
        used |= set(re.findall(r"<!-- table:([a-z0-9-]+) -->", p.read_text(encoding="utf-8")))
    assert used == set(tables.TABLES)


def test_a_table_edited_by_hand_is_caught_and_make_docs_restores_it(tmp_path):
    docs = _docs_copy(tmp_path)
    page = docs / "deorbit.md"
    original = page.read_text(encoding="utf-8")
    m = re.search(r"<!-- table:deorbit-run -->\n(.*?)<!-- /table -->", original, re.S)
    edited = original.replace(m.group(1), m.group(1).replace("| 1,755 |", "| 1,700 |"), 1)
    assert edited != original
    page.write_text(edited, encoding="utf-8")
    assert tables.stale(docs) == [str(page)]
    assert tables.main(["--check", "--docs", str(docs)]) == 1
    assert tables.update(docs) == [str(page)]
    assert page.read_text(encoding="utf-8") == original
    assert tables.main(["--check", "--docs", str(docs)]) == 0


def test_a_changed_json_changes_the_table(tmp_path):
    docs = _docs_copy(tmp_path)
    path = docs / "deorbit_bench.json"
    d = json.loads(path.read_text())
    d["energy_J"]["total"] = 1234.4
    path.write_text(json.dumps(d))
    assert tables.update(docs) == [str(docs / "deorbit.md")]
    assert "| energy total [J] | 1,234 | 1,755 |" in (docs / "deorbit.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("text, says", [
    ("<!-- table:no-such-table -->\nx\n<!-- /table -->\n", "unknown table 'no-such-table'"),
    ("<!-- table:deorbit-run -->\nno end marker\n", "without its"),
])
def test_bad_markers_are_one_line_errors(tmp_path, capsys, text, says):
    docs = _docs_copy(tmp_path)
    (docs / "extra.md").write_text(text, encoding="utf-8")
    assert tables.main(["--docs", str(docs)]) == 1
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1


def test_a_missing_json_is_named(tmp_path, capsys):
    docs = _docs_copy(tmp_path)
    (docs / "soak.json").unlink()
    assert tables.main(["--check", "--docs", str(docs)]) == 1
    assert "soak.json: missing" in capsys.readouterr().err


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(h) for h in re.findall(r"^#{1,6} (.+)$", text, re.M)}


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.S)
    for m in LINK.finditer(text):
        target = m.group(1) or m.group(2)
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name}: link to {target} goes nowhere"
        assert ROOT in dest.parents or dest == ROOT, f"{page.name}: link to {target} leaves the repository"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest), f"{page.name}: no heading for #{anchor} in {dest.name}"


def test_nothing_points_outside_the_repository_for_a_spec():
    hits = []
    for p in list(ROOT.glob("*.md")) + list(DOCS.rglob("*.md")) + [f for d in ("fsw", "hil", "ground", "bench", "tests")
                                                                   for f in (ROOT / d).rglob("*.py")]:
        for n, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"shared/(spec|papers)/", line):
                hits.append(f"{p.relative_to(ROOT)}:{n}")
    assert hits == []


def test_readme_is_a_front_door():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    headings = re.findall(r"^#{1,6} .+$", re.sub(r"```.*?```", "", text, flags=re.S), re.M)
    assert len(headings) == len(set(headings)), "a heading appears twice"
    for needed in ("make sitl", "make test", "Dependencies and why", "Quick start", "Layout"):
        assert needed in text


def test_the_ratio_interval_is_a_paired_bootstrap():
    """An IGRF row's ratio to its dipole row (docs/tables.py `ratio_interval`): runs that differ by one factor
    give that factor exactly; unpaired noise widens it around the pooled ratio; too few runs give none."""
    assert tables.ratio_interval([2.0, 4.0, 6.0, 1.0], [1.0, 2.0, 3.0, 0.5]) == pytest.approx((2.0, 2.0))
    rng = np.random.default_rng(5)
    den = list(rng.uniform(0.5, 1.5, 20))
    num = [d * f for d, f in zip(den, rng.uniform(0.8, 1.6, 20))]
    lo, hi = tables.ratio_interval(num, den)
    pooled = math.sqrt(sum(x * x for x in num) / sum(x * x for x in den))
    assert lo < pooled < hi and 0.8 < lo and hi < 1.6
    assert tables.ratio_interval(num, den) == (lo, hi)  # seeded
    assert all(math.isnan(x) for x in tables.ratio_interval([1.0], [1.0]))
