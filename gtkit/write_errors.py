"""What the machine, not gtkit, did wrong when a file could not be written or read: a full disk, a
used-up quota, a file-size limit, a read-only folder, a missing permission, a file removed under a
running stage. The command line (:mod:`gtkit.cli`) and ``gtkit run`` (:mod:`gtkit.run_site`) say it
in one line naming the file, instead of calling it a bug with a traceback."""
from __future__ import annotations

import errno

CAUSES = {
    errno.ENOSPC: "the disk is full: free space and run it again (finished stages are kept)",
    errno.EDQUOT: "the disk quota is used up: free space and run it again (finished stages are kept)",
    errno.EFBIG: "a file-size limit was reached (ulimit -f): raise it and run it again",
    errno.EROFS: "the folder is on a read-only file system",
    errno.EACCES: "permission denied: the folder is not writable (or readable) by this user",
    errno.EPERM: "operation not permitted for this user",
    errno.ENOENT: "no such file: was it moved or deleted while gtkit ran?",
    errno.EIO: "input/output error: the disk or network share failed",
}


def machine_cause(e: BaseException) -> str | None:
    """One line for an OSError the machine caused (``<file>: <cause>``), None for anything else
    (a bug, to be reported with its traceback)."""
    if not isinstance(e, OSError) or e.errno not in CAUSES:
        return None
    where = e.filename if e.filename is not None else None
    return f"{where}: {CAUSES[e.errno]}" if where else f"{e.strerror or type(e).__name__}: {CAUSES[e.errno]}"
