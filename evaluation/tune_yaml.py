"""The tuned config as a file: the original's text with the tuned values put in, its keys, order
and comments kept (ruamel.yaml's round trip), each changed value marked with a comment naming
the bag and the date."""

from __future__ import annotations

import io
from pathlib import Path

from ddfuse.evaluation.tune import TuneResult


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


def tuned_text(original: str, result: TuneResult, bag: str, date: str) -> str:
    """``original`` (a config's YAML text) with every value ``result`` tuned (status 'tuned' or
    at a bound) set to it (3 significant digits), a comment ``tuned`` on each (on the nearest
    enclosing block-style key where the value sits in a flow mapping, which holds no comments)
    and a header saying which bag, when and how. Keys the tuning did not touch keep their text."""
    from ruamel.yaml import YAML
    from ruamel.yaml.comments import CommentedMap

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
    for cm, key, names in notes.values():
        what = ", ".join(n for n in names if n)
        _set_eol(cm, key, f"tuned{': ' + what if what else ''} (ddfuse tune, {bag}, {date})")
    buf = io.StringIO()
    yaml.dump(data, buf)
    head = (f"# Noise values marked 'tuned' were estimated by `ddfuse tune` on {bag} ({date}):\n"
            f"# maximum likelihood of the {result.estimator} EKF's innovations "
            "(docs/design/tuning.md).\n")
    return head + buf.getvalue()


def _set_eol(cm, key, text: str) -> None:
    """Put ``# text`` at the end of ``key``'s line, replacing a comment the tuning made before
    (a re-tuned config keeps one)."""
    old = cm.ca.items.get(key)
    if old and old[2] is not None and "ddfuse tune" in old[2].value:
        old[2] = None
    cm.yaml_add_eol_comment(text, key)


def write_tuned(config_path: Path | None, out: Path, result: TuneResult, bag: str,
                date: str) -> None:
    """Write the tuned config to ``out`` (atomically): ``config_path``'s text with the tuned
    values (``tuned_text``); with no config file, a config of the tuned values alone."""
    from ddfuse.evaluation.atomic_files import write_text

    original = Path(config_path).read_text(encoding="utf-8") if config_path else ""
    write_text(out, tuned_text(original, result, bag, date))
