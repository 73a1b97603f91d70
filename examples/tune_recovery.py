"""Does ``ddfuse tune`` recover the true noise? Simulated bags whose config states the noise
they were drawn with, every measurement noise value started 3x too large or 3x too small, the
tuned value's error against the truth (the issue's 20-seed table, docs/design/tuning.md).

    python examples/tune_recovery.py run OUT.jsonl [--scenarios husky seed002] [--seeds 1-20]
        [--duration 120] [--jobs 1] [--trim S] [--factors 3 0.333] [--twist-rates]
    python examples/tune_recovery.py table OUT.jsonl

``run`` appends one JSON line per (scenario, seed, start) to OUT.jsonl and skips those already
there, so it can be stopped and resumed; ``--trim S`` tunes on the bag without its first and
last S seconds (every scenario starts and ends with a speed ramp from and to rest: cut, a
lawnmower's speed is constant, which the twist walk can describe; docs/design/tuning.md,
the odometry v's bias); ``table`` prints the markdown tables (per run, and per
value the median, the worst and how many of the runs are within 20 %). CPU seconds are this
process's and its workers' (``time.process_time`` does not see forked workers:
``os.times``' children).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np

TARGET = 0.20  # the issue's: each noise value within 20 % of the truth
PROCESS = ("slip", "walk", "twist", "common")


def _cpu() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def cut_ends(stream, seconds: float) -> None:
    """Drop ``stream``'s measurements and ground truth within ``seconds`` of its first and last
    message (in place; 0 keeps everything)."""
    if seconds <= 0.0:
        return
    a, b = stream.t0 + seconds, stream.t1 - seconds
    stream.measurements = [m for m in stream.measurements if a <= m.t <= b]
    stream.ground_truth = [g for g in stream.ground_truth if a <= g.t <= b]


def one(scenario: str, seed: int, factor: float, duration: float, jobs: int,
        trim: float = 0.0, twist_rates: bool = False) -> dict:
    """Simulate, tune from every stated measurement noise times ``factor`` (on the bag without
    its first and last ``trim`` s), and return the tuned values against the truth."""
    import subprocess
    import sys

    from ddfuse.estimation.bags import read_stream
    from ddfuse.estimation.config import load_config
    from ddfuse.evaluation.tune import tune, tuning_estimator
    from ddfuse.evaluation.tune_params import parameters

    with tempfile.TemporaryDirectory() as tmp:
        bag = Path(tmp) / f"{scenario}_{seed}.bag"
        ddfuse = Path(sys.executable).with_name("ddfuse")
        subprocess.run([str(ddfuse), "simulate", scenario, "--seed", str(seed), "--duration",
                        str(duration), "-o", str(bag)], check=True, capture_output=True)
        cfg = load_config(bag.with_suffix(".yaml"))
        stream = read_stream(bag, cfg)
        cut_ends(stream, trim)
        truth = {p.label: p.before for p in parameters(cfg, stream)
                 if p.kind not in PROCESS + ("corr",) and p.before is not None}
        c0 = _cpu()
        # (a landmark config tunes on ekf_landmark, which has no twist rates: one stage)
        res = tune(cfg, stream, start={k: v * factor for k, v in truth.items()}, jobs=jobs,
                   twist_rates=twist_rates and tuning_estimator(cfg) == "ekf")
        cpu = _cpu() - c0
    rows = {}
    for t in res.tuned:
        if t.param.label in truth:
            v = t.value
            rows[t.param.label] = {"truth": truth[t.param.label], "tuned": v,
                                   "status": t.status,
                                   "error": None if v is None or t.status == "not informed"
                                   else v / truth[t.param.label] - 1.0}
    return {"scenario": scenario, "seed": seed, "factor": factor, "trim": trim,
            "twist_rates": twist_rates, "values": rows,
            "runs": res.runs, "iterations": res.iterations, "cpu_s": cpu,
            "pairs": res.pairs, "message": res.message,
            "others": {t.param.label: [t.value, t.status] for t in res.tuned
                       if t.param.label not in truth}}


def _seeds(spec: str) -> list[int]:
    a, _, b = spec.partition("-")
    return list(range(int(a), int(b or a) + 1))


def run(out: Path, scenarios: list[str], seeds: list[int], duration: float, jobs: int,
        trim: float = 0.0, factors: tuple[float, ...] = (3.0, 1.0 / 3.0),
        twist_rates: bool = False) -> None:
    done = set()
    if out.exists():
        for line in out.read_text().splitlines():
            r = json.loads(line)
            done.add((r["scenario"], r["seed"], r["factor"]))
    for seed in seeds:
        for scenario in scenarios:
            for factor in factors:
                if (scenario, seed, factor) in done:
                    continue
                r = one(scenario, seed, factor, duration, jobs, trim, twist_rates)
                with out.open("a") as f:
                    f.write(json.dumps(r) + "\n")
                errs = {k: (None if v["error"] is None else round(100 * v["error"], 1))
                        for k, v in r["values"].items()}
                print(scenario, seed, "x3" if factor > 1 else "/3", errs,
                      f"{r['runs']} runs {r['cpu_s']:.0f} s CPU", flush=True)


def _cell(v: dict | None) -> str:
    if v is None:
        return ""
    if v["error"] is None:
        return "n.i."
    mark = "" if v["status"] == "tuned" else f" ({v['status']})"
    return f"{100 * v['error']:+.1f} %{mark}"


def table(out: Path) -> str:
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    lines = []
    for scenario in sorted({r["scenario"] for r in rows}):
        rs = sorted((r for r in rows if r["scenario"] == scenario),
                    key=lambda r: (r["seed"], -r["factor"]))
        labels = list(dict.fromkeys(k for r in rs for k in r["values"]))
        lines += [f"**{scenario}**", "",
                  "| seed, start | " + " | ".join(labels) + " | runs | CPU |",
                  "|---" * (len(labels) + 3) + "|"]
        for r in rs:
            start = "x3" if r["factor"] > 1 else "/3"
            lines.append(f"| {r['seed']}, {start} | "
                         + " | ".join(_cell(r["values"].get(k)) for k in labels)
                         + f" | {r['runs']} | {r['cpu_s']:.0f} s |")
        lines += ["", "| start | value | within 20 % | not informed | median error | "
                  "worst |", "|---|---|---|---|---|---|"]
        for start, sel in (("x3", lambda f: f > 1), ("/3", lambda f: f < 1)):
            for k in labels:
                vs = [r["values"][k] for r in rs if sel(r["factor"]) and k in r["values"]]
                e = np.array([v["error"] for v in vs if v["error"] is not None])
                ni = sum(v["error"] is None for v in vs)
                within = int(np.sum(np.abs(e) <= TARGET))
                med = f"{100 * np.median(e):+.1f} %" if len(e) else ""
                worst = f"{100 * e[np.argmax(np.abs(e))]:+.1f} %" if len(e) else ""
                lines.append(f"| {start} | {k} | {within} of {len(vs)} | {ni} | {med} | "
                             f"{worst} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--scenarios", nargs="+", default=["husky", "seed002"])
    r.add_argument("--seeds", default="1-20")
    r.add_argument("--duration", type=float, default=120.0)
    r.add_argument("--jobs", type=int, default=1)
    r.add_argument("--trim", type=float, default=0.0, help="s cut at each end before tuning")
    r.add_argument("--factors", type=float, nargs="+", default=[3.0, 1.0 / 3.0])
    r.add_argument("--twist-rates", action="store_true", help="tune --twist-rates")
    t = sub.add_parser("table")
    t.add_argument("out", type=Path)
    a = ap.parse_args()
    if a.cmd == "run":
        run(a.out, a.scenarios, _seeds(a.seeds), a.duration, a.jobs, a.trim, tuple(a.factors),
            a.twist_rates)
    else:
        print(table(a.out))


if __name__ == "__main__":
    main()
