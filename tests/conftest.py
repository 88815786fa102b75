"""pytest configuration: tests/ on the import path, so that `support` (shared helpers) is importable from
the sub-directories too; every test marked with its directory (fsw, hil, ground, sitl, bench), so that
`pytest -m ground` runs the ground's.

Hypothesis profiles (property-based tests; `support.tiers` makes a property into its two tests):

- ``fast`` (the default): 200 examples a property, so that the fast tier stays fast;
- ``fuzz``: 10,000 examples a property (the "at scale"). The ``slow``-marked variant of every
  fuzz property (``pytest -m slow``) always runs with it; ``HYPOTHESIS_PROFILE=fuzz`` makes every
  property that does not set its own count run with it too.

Both are derandomized (the examples are a function of the test's code: a failure reproduces on every
run and machine), without deadline (timing is the benchmarks' business) and without the health
checks that are about speed or size, which a slow shared machine fails for no fault of the code.
"""
import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, settings

sys.path.insert(0, str(Path(__file__).parent))
# ground.decode archives a live link's frames by default (ground.archive.default_path, under XDG_DATA_HOME):
# the tests' decoders, in process and in subprocesses, archive into a temporary directory
os.environ["XDG_DATA_HOME"] = tempfile.mkdtemp(prefix="debris-box-tests-")
atexit.register(shutil.rmtree, os.environ["XDG_DATA_HOME"], ignore_errors=True)

FUZZ_EXAMPLES = 10_000

_COMMON = dict(deadline=None, derandomize=True, print_blob=True,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                      HealthCheck.filter_too_much])
settings.register_profile("fast", max_examples=200, **_COMMON)
settings.register_profile("fuzz", max_examples=FUZZ_EXAMPLES, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))


LAYERS = ("fsw", "hil", "ground", "sitl", "bench")


def pytest_collection_modifyitems(config, items):
    here = Path(__file__).parent
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(here)
        if len(rel.parts) > 1 and rel.parts[0] in LAYERS:
            item.add_marker(rel.parts[0])
