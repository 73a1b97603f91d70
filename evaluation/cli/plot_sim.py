"""``ddfuse plot-sim SCENARIO -o OUT.png``: simulate a scenario and plot it."""

from __future__ import annotations

from pathlib import Path

from ddfuse.estimation.errors import DdfuseError
from ddfuse.evaluation import plot_sim as plot_sim_module
from ddfuse.evaluation.cli.arguments import DdfuseParser, int_at_least, simulated_scenario
from ddfuse.evaluation.cli.guard import guarded
from ddfuse.evaluation.cli.output_paths import check_output_file
from ddfuse.evaluation.plot_sim import plot_sim
from ddfuse.evaluation.simulate import SCENARIOS, simulate


def _main(argv: list[str] | None) -> int:
    from matplotlib.backend_bases import FigureCanvasBase

    ap = DdfuseParser(prog="ddfuse plot-sim",
                      description=plot_sim_module.__doc__.splitlines()[0])
    ap.add_argument("scenario", choices=list(SCENARIOS))
    ap.add_argument("--seed", type=int_at_least(0), default=0, help="random seed (default 0)")
    ap.add_argument("--duration", type=float, default=None, metavar="S",
                    help="seconds to simulate (default: the scenario's); shorter, the "
                    "scenario's drive for the seed cut to S s (ddfuse simulate --help)")
    ap.add_argument("-o", "--output", type=Path, required=True,
                    help="image path; its extension picks the format (.png, .pdf, .svg...)")
    args = ap.parse_args(argv)
    simulated_scenario(args.scenario, args.duration)
    kinds = FigureCanvasBase.get_supported_filetypes()
    ext = args.output.suffix[1:].lower()
    if ext and ext not in kinds:
        raise DdfuseError(f"-o {args.output}: cannot write a .{ext} image (formats: "
                          f"{', '.join(sorted(kinds))})")
    check_output_file(args.output, "-o")  # before simulating
    res = simulate(args.scenario, seed=args.seed, duration=args.duration)
    print(f"wrote {plot_sim(res, args.output)}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``ddfuse plot-sim SCENARIO [--seed N] [--duration S] -o OUT.png``; a user error ends in
    one line on stderr and exit code 2."""
    return guarded(_main, argv)
