"""Regenerate the reproduction table of docs/results/seed002_blog.md: the seed 002 post's filter
as its code wrote it, and with its defects fixed one at a time, over 20 seeds (about 2.5 min of
CPU). Usage: python docs/tools/seed002_blog_table.py [OUT.json]"""

import json
import sys

from ddfuse.evaluation.seed002_blog import BlogOptions, blog_table

OPTIONS = {
    "as written": BlogOptions(),
    "bearing relative to the heading": BlogOptions(global_bearing=False),
    "prediction along the filter's heading": BlogOptions(odometry_heading=False),
    "both": BlogOptions(global_bearing=False, odometry_heading=False),
    "both + the simulated noise in R, Q": BlogOptions(global_bearing=False,
                                                       odometry_heading=False,
                                                       stated_noise=False),
    "all fixed (3 states, known map)": BlogOptions(False, False, False, False),
}

if __name__ == "__main__":
    table = blog_table(range(20), OPTIONS)
    for name, row in table.items():
        print(f"| {name} | " + " | ".join(f"{row[k]:.3f}" for k in
                                          ("mean_error_m", "median_error_m", "max_error_m",
                                           "rmse_m")) + " |")
    if len(sys.argv) > 1:
        with open(sys.argv[1], "w") as f:
            json.dump(table, f, indent=1)
