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
