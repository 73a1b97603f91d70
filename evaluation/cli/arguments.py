"""What the commands share in parsing: the parser class, argument types and help texts.

An argument type raises ``argparse.ArgumentTypeError`` with what it expected; the parser turns
that into one line naming the sub-command and the option, and exit code 2.
"""

from __future__ import annotations

import argparse
import math
import re

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation.cli.terminal import one_line


class DdfuseParser(argparse.ArgumentParser):
    """The parser of ``ddfuse`` and of each sub-command: a usage error is one line,
    ``ddfuse: error: <sub-command>: <what> (see ddfuse <sub-command> --help)``, and exit code 2
    (argparse's own prints the usage block first and prefixes the sub-command's prog)."""

    def error(self, message: str):
        sub = self.prog.removeprefix("ddfuse").strip()
        where = f"{sub}: " if sub else ""
        hint = f"ddfuse {sub} --help" if sub else "ddfuse --help"
        self.exit(2, f"ddfuse: error: {where}{one_line(message)} (see {hint})\n")


CONFIG_HELP = ("config YAML (default: the bag's path with .yaml; else, for the real bags "
               "ddfuse ships a config for, data/configs/<bag's stem>.yaml)")

GPS_HOLDOUT_HELP = ("withhold these GPS fixes from every estimator and score against them: "
                    "every K-th fix (K >= 2), or the fixes from T0 to T1 s after the bag's first "
                    "message (0 <= T0 < T1)")


def plain_text(doc: str) -> str:
    """Sphinx/reST inline markup as plain text, for --help: ``:func:`a.b` `` -> ``a.b``,
    double back-quoted literals -> the literal."""
    doc = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", doc)
    return doc.replace("``", "")


def reorder_window(text: str) -> float:
    """argparse type of --reorder-window: seconds >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not v >= 0.0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return v


def add_reorder_window(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--reorder-window", type=reorder_window, metavar="S",
                    help="seconds of header-stamp disorder the decoder sorts out (messages "
                    "later than that are dropped and counted; default: the config's "
                    "reorder_window, 0.5 s)")


FOXGLOVE_PORT = 8765  # Foxglove's default WebSocket port


def port_number(text: str) -> int:
    """argparse type of a TCP port: 0..65535 (0: a free one)."""
    try:
        v = int(text)
    except ValueError:
        v = -1
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port 0..65535 (0: a free one), got "
                                         f"{text!r}")
    return v


def add_foxglove(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--foxglove", type=port_number, nargs="?", const=FOXGLOVE_PORT,
                    metavar="PORT",
                    help="serve the estimates live over the Foxglove WebSocket protocol on "
                    f"127.0.0.1:PORT (default {FOXGLOVE_PORT}; 0: a free one): in Foxglove, "
                    "Open connection, ws://127.0.0.1:PORT; needs the live extra (pip install "
                    "'ddfuse[live]')")


def lag_seconds(text: str) -> float:
    """argparse type of a smoother lag: seconds > 0 (the config's smoother.lag rule)."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (v > 0.0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}")
    return v


def int_at_least(minimum: int):
    """argparse type: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}"
                                             ) from None
        if v < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return v

    return parse


def estimator_list(text: str) -> list[str]:
    """argparse type of --estimators: comma-separated known estimator (or track) names; an
    empty list is refused (leave the option out for the default set)."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    return _estimator_names(text, list(TRACK_TO_SPEC))


def online_estimator_list(text: str) -> list[str]:
    """``estimator_list`` of ``online``: an unknown name is refused with the names online can
    run (not smoother_lagged or batch; asked for, those are refused with the reason by the
    ``online`` command)."""
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC
    from ddfuse.evaluation.online import ONLINE_TRACKS_REFUSED

    return _estimator_names(text, [n for n in TRACK_TO_SPEC if n not in ONLINE_TRACKS_REFUSED])


def _estimator_names(text: str, known: list[str]) -> list[str]:
    from ddfuse.evaluation.estimators import TRACK_TO_SPEC

    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated estimator names, got {text!r} (leave --estimators out "
            "for the default set)")
    unknown = [n for n in names if n not in TRACK_TO_SPEC]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown estimator {unknown[0]!r} (known: "
                                         f"{', '.join(known)})")
    return names


def gps_holdout(text: str) -> str:
    """argparse type of --gps-holdout: ``every:K`` (K >= 2) or ``window:T0:T1`` with
    0 <= T0 < T1, seconds from the bag's first message; returned as given."""
    from ddfuse.estimation.runner import parse_holdout

    try:
        parse_holdout(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("--gps-holdout: ")) from None
    return text


def simulated_scenario(name: str, duration: float | None):
    """The simulator scenario ``name`` (chosen from its list by argparse) with ``duration``;
    DdfuseError naming --duration when the duration is refused (before any work)."""
    from ddfuse.evaluation.simulate import get_scenario

    try:
        return get_scenario(name, duration)
    except ValueError as e:
        raise DdfuseError(f"--duration {duration:g}: {str(e).removeprefix('duration ')}"
                          ) from None
