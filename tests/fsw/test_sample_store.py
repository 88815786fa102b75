"""The box's sample store and resender: numbering, the ring, a file that survives a restart, requests
served within their budget."""
import numpy as np
import pytest

from fsw.telemetry.sample_store import MAX_REQUEST, Resender, SampleStore


def fill(store, n, t0=0.0):
    for k in range(n):
        store.append(t0 + 0.1 * k, np.array([1e-6 * k, 2e-6, -3e-6]))


def test_numbers_are_consecutive_and_the_ring_keeps_the_last_capacity():
    s = SampleStore(10, run_id=7)
    fill(s, 25)
    assert s.next_seq == 25 and s.first_seq == 15 and len(s) == 10
    assert s.get(14) is None and s.get(25) is None                  # forgotten, not yet taken
    run, t_us, b, flags, kit = s.get(20)
    assert flags == 0 and not kit.any()
    assert run == 7 and t_us == 2_000_000 and b[0] == pytest.approx(20e-6)


def test_a_file_store_survives_a_restart_and_the_numbering_goes_on(tmp_path):
    path = tmp_path / "samples.bin"
    s = SampleStore(100, run_id=1, path=path)
    fill(s, 30)
    s.close()                                   # (a killed process leaves the same: the pages are the file's)
    s2 = SampleStore(100, run_id=2, path=path)
    assert s2.persistent and s2.reset_reason == ""
    assert s2.run_first_seq == 30 and s2.next_seq == 30
    assert s2.get(29)[0] == 1 and s2.get(29)[1] == 2_900_000          # the previous run's sample, its run id
    seq = s2.append(5.0, np.zeros(3))
    assert seq == 30 and s2.get(30)[0] == 2


def test_a_slot_the_previous_run_did_not_finish_is_not_served(tmp_path):
    path = tmp_path / "samples.bin"
    s = SampleStore(100, path=path)
    fill(s, 10)
    s._seq[9] = 12345                           # as if killed while writing sample 9
    s.close()
    s2 = SampleStore(100, path=path)
    assert s2.get(9) is None and s2.get(8) is not None


@pytest.mark.parametrize("damage", ["short", "capacity"])
def test_a_store_of_another_size_is_moved_aside_never_loaded(tmp_path, damage):
    path = tmp_path / "samples.bin"
    if damage == "capacity":
        SampleStore(50, path=path).close()
    else:
        SampleStore(100, path=path).close()
        path.write_bytes(path.read_bytes()[:100])
    s = SampleStore(100, path=path)
    assert s.next_seq == 0 and s.persistent and s.reset_reason and (tmp_path / "samples.bin.bad").exists()


@pytest.mark.parametrize("kind", ["file", "folder", "link"])
def test_a_path_that_is_not_a_store_is_never_touched(tmp_path, kind):
    """A recording, a folder or a link given as the store by mistake stays as it was; the samples are
    kept in memory and the reason said."""
    path = tmp_path / "samples.bin"
    if kind == "file":
        path.write_bytes(b"t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n")
    elif kind == "folder":
        path.mkdir()
    else:
        (tmp_path / "target").write_bytes(b"x")
        path.symlink_to(tmp_path / "target")
    before = sorted(p.name for p in tmp_path.iterdir())
    s = SampleStore(100, path=path)
    fill(s, 5)
    assert not s.persistent and "not a sample store" in s.reset_reason and s.get(4) is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    if kind == "file":
        assert path.read_bytes().startswith(b"t_s,")


def send_log(sent, bytes_per_frame=50, down=False):
    def send(seq, run_id, t_us, b, flags, kit_T):
        if down:
            return None
        sent.append(seq)
        return bytes_per_frame
    return send


def test_requests_are_served_within_the_budget_oldest_first():
    s = SampleStore(1000)
    fill(s, 500)
    r = Resender(s, bytes_per_s=1000.0)
    assert r.request(100, 100) and r.request(10, 5)
    sent = []
    for k in range(1, 41):                      # 4 s at 10 Hz
        r.service(0.1 * k, send_log(sent))
    # 1000 B/s at 50 B a frame: 20 a second, + at most one frame that overdraws the budget per tick
    assert 4 * 20 - 2 <= len(sent) <= 4 * 20 + 2
    assert sent[:10] == list(range(100, 110))
    assert r.queued == 105 - len(sent) and r.resent == len(sent)


def test_overlapping_requests_merge_bad_ones_are_refused_and_counted():
    s = SampleStore(1000)
    fill(s, 300)
    r = Resender(s, max_ranges=2)
    assert r.request(10, 20) and r.request(20, 20)                      # merged: 10..39
    assert r.queued == 30
    assert not r.request(0, 0) and not r.request(-5, 3) and not r.request(0, MAX_REQUEST + 1)
    assert not r.request(300, 5)                                        # nothing sent under that number yet
    assert r.request(100, 5) and not r.request(200, 5)                  # the queue holds two ranges
    assert r.refused == 5 and r.requests == 3


def test_samples_no_longer_held_are_skipped_and_a_down_link_pauses():
    s = SampleStore(100)
    fill(s, 250)                                # holds 150..249
    r = Resender(s, bytes_per_s=1e6)
    r.request(100, 60)
    sent = []
    r.service(0.0, send_log(sent))
    r.service(1.0, send_log(sent, down=True))
    assert sent == [] and r.queued == 10        # 100..149 skipped at once, 150..159 wait for the link
    assert r.unavailable == 50
    r.service(2.0, send_log(sent))
    assert sent == list(range(150, 160))


def test_flags_and_the_kit_field_are_kept_in_the_file_and_resent(tmp_path):
    """A sample taken while the kit moved keeps its flag and the kit field the box took out of it, across a
    restart, and the resender hands both on."""
    path = tmp_path / "samples.bin"
    s = SampleStore(100, run_id=1, path=path)
    s.append(0.0, np.array([1e-6, 2e-6, 3e-6]))
    s.append(0.1, np.array([60e-6, 2e-6, 3e-6]), 2, np.array([59e-6, -1e-6, 0.5e-6]))
    s.close()
    s2 = SampleStore(100, run_id=2, path=path)
    _, _, _, flags0, kit0 = s2.get(0)
    _, _, _, flags1, kit1 = s2.get(1)
    assert flags0 == 0 and not kit0.any()
    assert flags1 == 2 and kit1 == pytest.approx([59e-6, -1e-6, 0.5e-6], abs=1e-15)
    got = []
    r = Resender(s2)
    r.request(0, 2)
    r.service(0.0, lambda *a: got.append(a) or 50)
    r.service(1.0, lambda *a: got.append(a) or 50)
    assert [(a[0], a[4]) for a in got] == [(0, 0), (1, 2)] and got[1][5][0] == pytest.approx(59e-6)


def test_a_store_file_of_the_older_layout_is_moved_aside(tmp_path):
    path = tmp_path / "samples.bin"
    path.write_bytes(b"DEBRIS-SAMPLES-1" + bytes(16 + 48 * 100))
    s = SampleStore(100, path=path)
    assert s.persistent and "moved to samples.bin.bad" in s.reset_reason and s.next_seq == 0
    assert (tmp_path / "samples.bin.bad").exists()
