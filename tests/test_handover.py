"""The interpreter's switch interval lowered while threads launch GPU work, and put back after
the last of them, however they overlap."""

import sys
import threading

from gaussian_atoms_method.launch.handover import HANDOVER_S, quick_handover


def test_nested_and_concurrent_users_put_the_interval_back_after_the_last():
    before = sys.getswitchinterval()
    inside, release = threading.Event(), threading.Event()

    def other():
        with quick_handover():
            inside.set()
            release.wait(10)

    thread = threading.Thread(target=other)
    with quick_handover():
        thread.start()
        assert inside.wait(10)
        with quick_handover():
            assert sys.getswitchinterval() == min(before, HANDOVER_S)
    # the first user is done; the other thread still launches work
    assert sys.getswitchinterval() == min(before, HANDOVER_S)
    release.set()
    thread.join()
    assert sys.getswitchinterval() == before


def test_a_shorter_interval_of_the_users_own_is_kept():
    before = sys.getswitchinterval()
    try:
        sys.setswitchinterval(HANDOVER_S / 10)
        own = sys.getswitchinterval()  # the interpreter keeps whole microseconds
        with quick_handover():
            assert sys.getswitchinterval() == own
        assert sys.getswitchinterval() == own
    finally:
        sys.setswitchinterval(before)
