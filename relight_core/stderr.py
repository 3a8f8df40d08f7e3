"""Keep C libraries' own error lines about a file off stderr: our InputError already says it in one sentence.

OpenEXR's core prints e.g. `/path/x.exr: (EXR_ERR_BAD_CHUNK_LEADER) Preparing to read scanline 0 ...`
straight to file descriptor 2 before raising. `quiet_about(path)` points fd 2 at a temporary file
for the duration of the block, then writes back every captured line except those about `path`, so
output from other threads is delayed, never lost. Blocks are serialised by a lock.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading

_lock = threading.Lock()


@contextlib.contextmanager
def quiet_about(path):
    """Drop stderr lines that mention `path` (written by C code inside the block); keep all others."""
    path = os.fspath(path)
    names = (path, os.path.abspath(path))
    with _lock:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError):  # no usable fd 2: nothing to protect
            yield
            return
        with tempfile.TemporaryFile() as captured:
            os.dup2(captured.fileno(), 2)
            try:
                yield
            finally:
                try:
                    sys.stderr.flush()
                except (OSError, ValueError):
                    pass
                os.dup2(saved, 2)
                os.close(saved)
                captured.seek(0)
                kept = [line for line in captured.read().decode("utf-8", "replace").splitlines(keepends=True)
                        if not any(name in line for name in names)]
                if kept:
                    os.write(2, "".join(kept).encode())
