"""``python -m ddfuse.evaluation.cli``: the ``ddfuse`` command."""

from ddfuse.evaluation.cli.dispatch import entry

entry()
