"""Where `erva run` keeps a session's params file and node logs, and when they go.

A run's directory is ``<tmp>/erva_run_<pid of erva run>_<random>`` unless the user names
one.  A run removes its own when it ends well and keeps it when it failed (with its
errors in ``FAILED_NOTE``); a run killed with SIGKILL can do neither, so the next run
removes the directories of runs that are gone (:func:`remove_stale_session_dirs`).
"""

import os
import shutil
import tempfile
from typing import List, Optional

#: Temporary session directories: <tmp>/erva_run_<pid of erva run>_<random>.
SESSION_DIR_PREFIX = 'erva_run_'
#: In the session directory of a failed run: its errors (and the directory is kept).
FAILED_NOTE = 'failed.txt'


def remove_stale_session_dirs(parent: Optional[str] = None) -> List[str]:
    """Remove the temporary session directories of `erva run` processes that are gone.

    A run removes its own when it ends well, and keeps it when it failed (with the errors
    in ``FAILED_NOTE``); a run killed with SIGKILL can do neither, so the next one removes
    a directory whose owner's pid (in its name) no longer runs and that no failure kept.
    Returns the removed paths.
    """
    parent = parent or tempfile.gettempdir()
    removed = []
    for name in sorted(os.listdir(parent)):
        if not name.startswith(SESSION_DIR_PREFIX):
            continue
        pid = name[len(SESSION_DIR_PREFIX):].split('_', 1)[0]
        path = os.path.join(parent, name)
        if (not pid.isdigit() or int(pid) == os.getpid() or _alive(int(pid))
                or os.path.exists(os.path.join(path, FAILED_NOTE))):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


__all__ = ['SESSION_DIR_PREFIX', 'FAILED_NOTE', 'remove_stale_session_dirs']
