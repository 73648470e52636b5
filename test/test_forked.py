"""A call in a forked child gives its value or raises its exception in the caller; a child
that dies or is no longer wanted never hangs the caller; with threads the call runs inline."""

from __future__ import annotations

import subprocess
import sys
import threading

import pytest

from csam_ros.forked import Forked, can_fork

# run in a fresh process: the test process may hold threads (in-process nodes), and only a
# process without them forks
CALLS = """
import os, threading, time
from csam_ros.forked import Forked, can_fork

class Refused(Exception):
    pass

def value(n):
    return {"pid": os.getpid(), "squares": [i * i for i in range(n)]}

def refuse(text):
    raise Refused(text)

def die():
    os._exit(3)

def unpicklable():
    return threading.Lock()

assert can_fork()
got = Forked(value, 4).result()
print("value", got["pid"] != os.getpid(), got["squares"])
try:
    Forked(refuse, "no such bag").result()
except Refused as err:
    print("raised", type(err).__name__, err)
for call in (die, unpicklable):
    try:
        Forked(call).result()
    except RuntimeError as err:
        print("failed", call.__name__, err)
start = time.monotonic()
slow = Forked(time.sleep, 60)
slow.close()
print("closed", time.monotonic() - start < 30)
"""


def test_a_forked_call_gives_its_value_its_error_or_a_reason() -> None:
    done = subprocess.run(
        [sys.executable, "-c", CALLS], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        "value True [0, 1, 4, 9]",
        "raised Refused no such bag",
        "failed die its process ended without a word",
        "failed unpicklable TypeError: cannot pickle '_thread.lock' object",
        "closed True",
    ]


def test_with_other_threads_the_call_runs_in_the_caller() -> None:
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not can_fork()
        assert Forked(threading.get_ident).result() == threading.get_ident()
        with pytest.raises(ZeroDivisionError):
            Forked(divmod, 1, 0).result()
    finally:
        stop.set()
        other.join()
