"""The ``ddfuse`` command line: argument parsing and terminal printing, one module per command.

The work is done by the library; no library module imports this package (a test walks the
imports). ``entry`` is the console script, ``main(argv)`` the same returning the exit code.

Every user error (bad config, unreadable bag, absent topic, ...) ends in one line on stderr
naming the file, topic, field or key, and exit code 2: never a traceback (``guard``).

Modules: ``dispatch`` (the top-level parser, ``main``, ``entry``); the commands ``inspect``,
``run``, ``report``, ``online``, ``bench`` (registered in the top-level parser) and
``simulate``, ``plot_sim``, ``lag_sweep``, ``mc`` (each parsing its own arguments); what they
share: ``arguments`` (the parser class, argument types, help texts), ``output_paths`` (output
checks before any work), ``guard`` (the error handling), ``terminal`` (formatting, progress).
"""

from ddfuse.evaluation.cli.dispatch import entry, main

__all__ = ["entry", "main"]
