"""The command line's error handling: a user error is one line on stderr and exit code 2.

The exit codes (the README's list): 0 done; 2 an error in the input, an option or an output
path (one line); 3 ``run`` wrote its results but every estimator ended in ERROR
(``NO_ESTIMATE``); 130 Ctrl-C, 143 SIGTERM (a run writes the results of what it had first);
141 the reader of stdout went away."""

from __future__ import annotations

import sys

from ddfuse.estimation.errors import DdfuseError
from ddfuse.estimation.interrupts import sigterm_received

NO_ESTIMATE = 3  # exit code: results written, but no estimator gave any without an error


def guarded(func, *args) -> int:
    """``func(*args)`` with ddfuse's error handling: a DdfuseError, or an OSError on a path
    (an output directory that is a file, a full disk...), ends in one line on stderr and exit
    code 2; Ctrl-C in 130, SIGTERM (taken as Ctrl-C: ``interrupts.terminate_as_interrupt``)
    in 143. Anything else (a bug) propagates with its traceback."""
    try:
        return func(*args) or 0
    except DdfuseError as e:
        print(f"ddfuse: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        raise  # a reader that stopped early: entry() ends quietly
    except OSError as e:  # an output path that cannot be written: a directory that is a file...
        where = f"{e.filename}: " if e.filename else ""
        what = " (a file where a directory is needed)" if isinstance(
            e, (FileExistsError, NotADirectoryError)) else ""
        print(f"ddfuse: error: {where}{e.strerror or e}{what}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:
        print(f"ddfuse: {e}" if str(e) else "ddfuse: interrupted", file=sys.stderr)
        return 143 if sigterm_received() else 130
