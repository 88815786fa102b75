"""The kit columns of a recording: written and read back, optional (an old file reads as before), and taken
out by ground.kit_field.take_out (flagged samples skipped, the kit field subtracted) for ground.inertia
and ground.replay as for ground.estimate."""
import numpy as np
import pytest

from ground import kit_field
from ground import replay as gr
from ground.recording import Recording, RecordingError, read_recording, write_recording


def kit_recording(n=200, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.1
    earth = np.column_stack([np.cos(0.2 * t), np.sin(0.2 * t), np.full(n, 0.6)]) * 35e-6
    kit = np.zeros((n, 3))
    kit[n // 2:] = [60e-6, -20e-6, 5e-6]           # a capsule opened: a 64 µT step
    flags = np.zeros(n, dtype=np.int64)
    flags[n // 2 - 5:n // 2] = 2                    # while its shutter moved
    b = earth + kit + rng.normal(0, 0.1e-6, (n, 3))
    return Recording(t, b, kit_T=kit, flags=flags, metadata={"source": "test"}), earth


def test_the_kit_columns_round_trip_and_are_optional(tmp_path):
    rec, _ = kit_recording()
    write_recording(tmp_path / "k.csv", rec)
    back = read_recording(tmp_path / "k.csv")
    assert back.kit_T == pytest.approx(rec.kit_T, abs=1e-15) and (back.flags == rec.flags).all()
    header = [x for x in (tmp_path / "k.csv").read_text().splitlines() if not x.startswith("#")][0]
    assert header.endswith("kit_bx_uT,kit_by_uT,kit_bz_uT,flags")
    write_recording(tmp_path / "old.csv", Recording(rec.t_s, rec.b_T))
    old = read_recording(tmp_path / "old.csv")
    assert old.kit_T is None and old.flags is None
    assert kit_field.take_out(old)[0] is old


def test_a_flags_cell_that_is_not_a_byte_is_refused_with_its_line(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t_s,bx_uT,by_uT,bz_uT,flags\n0,30,0,20,0\n0.1,30,0,20,2.5\n")
    with pytest.raises(RecordingError, match=r"bad.csv:3: column 'flags'"):
        read_recording(p)


def test_take_out_skips_flagged_samples_and_subtracts_the_kit(tmp_path):
    rec, earth = kit_recording()
    out, line = kit_field.take_out(rec)
    keep = rec.flags == 0
    assert len(out) == 195 and out.t_s == pytest.approx(rec.t_s[keep])
    assert np.abs(out.b_T - earth[keep]).max() < 1e-6   # the step is gone: only the noise is left
    assert line.startswith("kit field: 5 of 200 samples flagged KIT_MOVING skipped; the recorded kit field "
                           "subtracted from 100 samples (up to 63.4 µT")
    raw, line = kit_field.take_out(rec, raw=True)
    assert raw is rec and line.startswith("kit field: kept raw (--kit-raw): 5 of 200")


def test_replay_and_inertia_take_the_kit_out_first(tmp_path, capsys):
    rec, earth = kit_recording()
    write_recording(tmp_path / "k.csv", rec)
    src = gr.RecordingReplay.from_csv(tmp_path / "k.csv", warn=lambda _: None)
    assert len(src.t) == 195 and np.abs(src.b - earth[rec.flags == 0]).max() < 1e-6
    assert src.kit_line.startswith("kit field: 5 of 200 samples flagged KIT_MOVING skipped")
    raw = gr.RecordingReplay.from_csv(tmp_path / "k.csv", warn=lambda _: None, kit_raw=True)
    assert len(raw.t) == 200
    from ground import inertia as gi
    gi.main([str(tmp_path / "k.csv"), str(tmp_path / "i.json"), "--quiet"])
    assert capsys.readouterr().out.splitlines()[0].startswith("kit field: 5 of 200 samples flagged KIT_MOVING")
