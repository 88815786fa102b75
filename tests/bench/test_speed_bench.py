"""bench.speed's sweep, shortened: the figures it reports are the loop's own counters, consistent with each
other, and its JSON is what docs/tables.py renders."""
import json

from bench import speed


def test_speed_bench_reports_a_consistent_sweep(tmp_path, capsys):
    out = tmp_path / "speed.json"
    assert speed.main(["--duration", "0.5", "--rates", "200", "--slowdown", "2", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    fixed, auto = d["runs"]
    assert (fixed["rate_hz"], fixed["slowdown"], fixed["adaptive"], auto["adaptive"]) == (200.0, 2.0, False, True)
    for r in (fixed, auto):
        assert r["ticks"] >= 480 and r["received"] > 90   # fewer ticks when some ran late
        assert r["produced"] == r["received"] + r["lost_in_chip"]
        assert r["processed"] + r["waiting"] + r["refused"] == r["received"]
        assert 0 < r["p50_us"] <= r["p99_us"] <= r["max_us"]
    assert d["highest_held_hz"]["x2"] in (None, 200.0) and d["chosen_hz"]["x2"] == auto["final_rate_hz"]
    assert "held" in capsys.readouterr().out


def test_speed_bench_refuses_bad_rates(capsys):
    import pytest
    with pytest.raises(SystemExit) as e:
        speed.main(["--rates", "2000"])
    assert e.value.code == 2 and "rates must be in (0, 1000]" in capsys.readouterr().err
