"""The speed table printed by `make bench` (tests/bench/report.py) from a benchmark JSON."""
import importlib.util
from pathlib import Path

spec = importlib.util.spec_from_file_location("bench_report", Path(__file__).with_name("report.py"))
report = importlib.util.module_from_spec(spec)
spec.loader.exec_module(report)


def bench(**medians_s):
    return {"benchmarks": [{"name": n, "stats": {"median": v}} for n, v in medians_s.items()],
            "machine_info": {"cpu": {"brand_raw": "Test CPU"}, "python_version": "3.11.7"},
            "datetime": "2026-11-21T10:00:00"}


def test_table_reports_medians_ratio_and_throughput():
    text = report.table(bench(test_loop_tick=80e-6, test_kalman_step=4e-6, test_filterpy_kalman_step=16e-6,
                              test_ground_parse=10e-3, test_driver_decode=0.5e-6))
    assert "| `test_loop_tick` | 80.0 µs | ≤ 100 µs | yes |" in text
    assert "ratio 4.0×" in text
    assert "100,000 frames/s" in text
    assert "Test CPU, Python 3.11.7, 2026-11-21" in text


def test_table_says_when_a_target_misses():
    text = report.table(bench(test_loop_tick=150e-6, test_kalman_step=8e-6, test_filterpy_kalman_step=16e-6))
    assert "| `test_loop_tick` | 150.0 µs | ≤ 100 µs | NO |" in text
    assert "ratio 2.0×" in text and text.count("| NO |") == 3


def test_usage_without_a_file(capsys):
    assert report.main([]) == 2
    assert "bench.json" in capsys.readouterr().err
