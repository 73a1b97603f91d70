"""``python -m ddfuse``: the ``ddfuse`` command."""

from ddfuse.evaluation.cli import entry

entry()
