"""The tuned config as a file: the original's text with the tuned values put in, its keys, order
and comments kept (ruamel.yaml's round trip), each changed value marked with a comment naming
the bag and the date."""

from __future__ import annotations

import io
import textwrap
from pathlib import Path

from ddfuse.evaluation.tune import HOLDOUT_WHY, Check, TuneResult, holdout_rise

HEAD = "# Noise values marked 'tuned' were estimated by `ddfuse tune`"


def _path(key: str) -> list:
    """``sensors.imu[0].noise.yaw`` -> ['sensors', 'imu', 0, 'noise', 'yaw']."""
    out: list = []
    for part in key.split("."):
        if "[" in part:
            name, i = part[:-1].split("[")
            out += [name, int(i)]
        else:
            out.append(part)
    return out


def _round(v: float) -> float:
    return float(f"{v:.3g}")


def _without_head(original: str) -> str:
    """``original`` without the header an earlier ``ddfuse tune`` put on it: a re-tuned config
    carries this tuning's header only. The header is the comment block up to its blank line;
    before the hold-out lines it had no blank line and was two lines."""
    if not original.startswith(HEAD):
        return original
    lines = original.splitlines(keepends=True)
    for i, line in enumerate(lines):
        if not line.strip():
            return "".join(lines[i + 1:])
        if not line.startswith("#"):
            break
    return "".join(lines[2:])


def _validation(result: TuneResult, before: Check | None, after: Check | None,
                holdout: str | None) -> list[str]:
    """The header's lines on how the tuned values did against the config's: the tuning
    estimator's sensors with a NIS verdict Fail, and with a hold-out its RMSE (m), flagged
    when worse (``holdout_rise``)."""
    if before is None or after is None:
        return []

    def fails(c: Check) -> int:
        return sum(1 for s in c.nis.values() if s.nis.verdict == "Fail")

    out = [f"NIS verdict Fail on {fails(before)} -> {fails(after)} of "
           f"{len(after.nis)} sensors (the {result.estimator} EKF, config's -> tuned values)."]
    b, a = before.holdout_rmse_m, after.holdout_rmse_m
    if holdout and b is not None and a is not None:
        nb, na = before.holdout_nees, after.holdout_nees
        nees = (f"; NEES {nb.brief()} -> {na.brief()} (expected 2: whether the covariance "
                "covers the error)"
                if nb is not None and na is not None else "")
        out.append(f"Validated on the fixes withheld by --gps-holdout {holdout}: RMSE "
                   f"{b:.3f} m with the config's values, {a:.3f} m tuned{nees}.")
    rise = holdout_rise(before, after, holdout)
    if rise is not None:
        out.append(f"WORSE by {100.0 * rise:.0f} % on that hold-out: {HOLDOUT_WHY}.")
    return out


def tuned_text(original: str, result: TuneResult, bag: str, date: str,
               before: Check | None = None, after: Check | None = None,
               holdout: str | None = None, gps_model: str | None = None) -> str:
    """``original`` (a config's YAML text) with every value ``result`` tuned (status 'tuned' or
    at a bound) set to it (3 significant digits), a comment ``tuned`` on each (on the nearest
    enclosing block-style key where the value sits in a flow mapping, which holds no comments)
    and a header saying which bag, when and how, and with the ``check`` runs of the config's
    and the tuned values (``before``, ``after``) how they compare, on the ``holdout`` spec's
    withheld fixes too. Keys the tuning did not touch keep their text; an earlier tuning's
    header is replaced. ``gps_model``: the ``gps.model`` the values were tuned under where the
    command line set it (``ddfuse run --tune --gps-model``), put in with a comment saying so."""
    from ruamel.yaml import YAML
    from ruamel.yaml.comments import CommentedMap

    original = _without_head(original)
    yaml = YAML(typ="rt")
    yaml.preserve_quotes = True
    yaml.width = 100
    data = yaml.load(original) if original.strip() else None
    if data is None:
        data = CommentedMap()
    notes: dict[tuple[int, object], tuple[CommentedMap, object, list[str]]] = {}
    for t in result.tuned:
        if t.value is None or t.status == "not informed":
            continue
        path = _path(t.param.key)
        node, anchor = data, None  # anchor: (mapping, key) of the innermost block-style key
        for k, nxt in zip(path[:-1], path[1:], strict=True):
            child = node[k] if (isinstance(node, list) and k < len(node)) or (
                not isinstance(node, list) and k in node) else None
            if child is None:
                child = CommentedMap()
                if not isinstance(nxt, int) and node is not data:
                    child.fa.set_flow_style()
                node[k] = child
            if isinstance(node, CommentedMap) and not node.fa.flow_style():
                anchor = (node, k)
            node = child
        node[path[-1]] = _round(t.value)
        if isinstance(node, CommentedMap) and not node.fa.flow_style():
            anchor = (node, path[-1])
        if anchor is not None:
            entry = notes.setdefault((id(anchor[0]), anchor[1]), (anchor[0], anchor[1], []))
            entry[2].append(path[-1] if anchor[1] != path[-1] else "")
    if gps_model is not None:
        gps = data.get("gps")
        if not isinstance(gps, CommentedMap):
            gps = data["gps"] = CommentedMap()
        gps["model"] = gps_model
        anchor = (gps, "model") if not gps.fa.flow_style() else (data, "gps")
        _set_eol(*anchor, f"tuned under --gps-model {gps_model} (ddfuse tune, {bag}, {date})")
    for cm, key, names in notes.values():
        what = ", ".join(n for n in names if n)
        _set_eol(cm, key, f"tuned{': ' + what if what else ''} (ddfuse tune, {bag}, {date})")
    buf = io.StringIO()
    yaml.dump(data, buf)
    text = (f"{HEAD[2:]} on {bag} ({date}): maximum likelihood of the {result.estimator} "
            "EKF's innovations (docs/design/tuning.md).")
    head = [text] + _validation(result, before, after, holdout)
    wrapped = [w for line in head for w in textwrap.wrap(line, 96, break_long_words=False,
                                                          break_on_hyphens=False)]
    return "".join(f"# {w}\n" for w in wrapped) + "\n" + buf.getvalue()


def _set_eol(cm, key, text: str) -> None:
    """Put ``# text`` at the end of ``key``'s line, replacing a comment the tuning made before
    (a re-tuned config keeps one)."""
    old = cm.ca.items.get(key)
    if old and old[2] is not None and "ddfuse tune" in old[2].value:
        old[2] = None
    cm.yaml_add_eol_comment(text, key)


def write_tuned(config_path: Path | None, out: Path, result: TuneResult, bag: str,
                date: str, before: Check | None = None, after: Check | None = None,
                holdout: str | None = None, gps_model: str | None = None) -> None:
    """Write the tuned config to ``out`` (atomically): ``config_path``'s text with the tuned
    values (``tuned_text``, with the checks' comparison in its header); with no config file, a
    config of the tuned values alone."""
    from ddfuse.evaluation.atomic_files import write_text

    original = Path(config_path).read_text(encoding="utf-8") if config_path else ""
    write_text(out, tuned_text(original, result, bag, date, before, after, holdout, gps_model))
