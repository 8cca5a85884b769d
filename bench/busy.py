"""A busy loop on every core, as another job on the same machine would keep them.

What a benchmark or a test measures "on a busy machine" runs inside
`busy_loop_on_every_core`: one process per core spinning at the default priority,
each ended by its pid when the block ends, however it ends.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def busy_loop_on_every_core() -> Iterator[list[int]]:
    """Processes spinning, one per core (their pids); each ended when the block ends."""
    spinners = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"])
        for _ in range(os.cpu_count() or 1)
    ]
    try:
        yield [spinner.pid for spinner in spinners]
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait(timeout=30)
