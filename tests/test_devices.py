"""`coopjax.devices`: a program compiled ahead of time once per process, whichever threads ask for it
(the tuner compiles its later programs in a background thread while its first ones run)."""

import threading
import time

import numpy as np
import pytest

from coopjax import devices


class Slow:
    """A stand-in for a jitted function: `lower(x).compile()` takes a while and is counted."""

    def __init__(self, fail_first=False):
        self.compiles, self.fail_first = 0, fail_first

    def lower(self, x):
        return self

    def compile(self):
        self.compiles += 1
        time.sleep(0.2)
        if self.fail_first and self.compiles == 1:
            raise ValueError("a compile that fails")
        return ("executable", self.compiles)


def test_a_program_that_two_threads_ask_for_at_once_is_compiled_once():
    program, got = Slow(), []
    threads = [threading.Thread(target=lambda: got.append(devices.compiled(program, np.ones(3)))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert program.compiles == 1
    assert got == [("executable", 1)] * 3


def test_a_failed_compile_reaches_the_caller_and_the_next_call_compiles_again():
    program = Slow(fail_first=True)
    with pytest.raises(ValueError, match="a compile that fails"):
        devices.compiled(program, np.ones(3))
    assert devices.compiled(program, np.ones(3)) == ("executable", 2)
    assert devices.compiled(program, np.ones(3)) == ("executable", 2)  # kept from then on
