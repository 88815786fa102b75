"""pytest configuration: tests/ on the import path, so that `support` (shared helpers) is importable from
the sub-directories too; every test marked with its directory (fsw, hil, ground, sitl, bench), so that
`pytest -m ground` runs the ground's."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

LAYERS = ("fsw", "hil", "ground", "sitl", "bench")


def pytest_collection_modifyitems(config, items):
    here = Path(__file__).parent
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(here)
        if len(rel.parts) > 1 and rel.parts[0] in LAYERS:
            item.add_marker(rel.parts[0])
