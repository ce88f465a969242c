"""`mi_amr.parallel.ordered_map`: results in the order of the stream, a
bounded number of items pulled ahead, errors raised where they happen."""

import threading
import time

import pytest

from mi_amr.parallel import ordered_map


def test01_results_come_in_order_with_a_bounded_look_ahead():
    pulled, done = [], []

    def items():
        for i in range(40):
            pulled.append(i)
            yield i

    def work(i):
        time.sleep(0.002 * ((7 * i) % 5))          # finish out of order
        return i * i, threading.get_ident()

    out = []
    for k, (sq, tid) in enumerate(ordered_map(work, items(), threads=2, ahead=4)):
        assert len(pulled) <= k + 4                # never more than 4 items ahead of the consumer
        out.append(sq)
        done.append(tid)
    assert out == [i * i for i in range(40)]
    assert len(set(done)) == 2                     # both threads worked
    assert [i * i for i in range(5)] == list(x for x, _ in ordered_map(work, range(5), threads=1))


def test02_an_error_is_raised_in_order_and_stops_the_stream():
    pulled = []

    def items():
        for i in range(1000):
            pulled.append(i)
            yield i

    def work(i):
        if i == 5:
            raise ValueError("chunk 5 is bad")
        return i

    got = []
    with pytest.raises(ValueError, match="chunk 5"):
        for x in ordered_map(work, items(), threads=2, ahead=3):
            got.append(x)
    assert got == [0, 1, 2, 3, 4] and len(pulled) < 20


def test03_progress_bars_end_at_their_totals(llvm, tmp_path, monkeypatch):
    """Every bar of a load, the default builds and a conversion to .amrb
    has a total (so it shows an ETA) and ends exactly there: the ETA counts
    every step the bar stands for."""
    import io

    import mitsuba as mi
    from tqdm import tqdm

    import mi_amr.progress
    from mi_amr.data.amrb import read_amrb, write_amrb
    from mi_amr.data.datasets import write_block_dataset
    bars = []

    class Recorded(tqdm):
        def __init__(self, *args, **kwargs):
            kwargs.update(disable=False, file=io.StringIO())      # counted as on a terminal
            super().__init__(*args, **kwargs)
            self.what = kwargs.get("desc", "")

        def close(self):
            if not getattr(self, "_recorded", False):
                self._recorded = True
                bars.append((self.what, self.total, self.n))
            super().close()
    monkeypatch.setattr(mi_amr.progress, "tqdm", Recorded)
    path = write_block_dataset(tmp_path / "p.cells", 60_000, 3, nxb=(8, 16))
    med = mi.load_dict({"type": "amr", "filename": str(path), "reconstruction": "nearest"})
    write_amrb(med.volume, tmp_path / "p.amrb")
    read_amrb(tmp_path / "p.amrb")
    names = [d.split(" ")[0] for d, _, _ in bars]
    for step in ("loading", "macrocell", "value", "writing", "reading"):
        assert step in names, (step, bars)
    for desc, total, n in bars:
        assert total is not None and total > 0 and n == total, (desc, total, n)
