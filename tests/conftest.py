"""pytest configuration: tests/ on the import path, so that `support` (shared helpers) is importable from
the sub-directories too (tests/benchmarks)."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
