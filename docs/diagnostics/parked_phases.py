# parked_phases.py - where MA-DBP loses time in the parked scene of four (docs/experiments.md,
# "Best of two for small teams"): robots 0 and 1 travel, robots 2 and 3 start parked on their
# goals. From each successful episode's SVG: the step the last traveller first comes within 0.3
# of its goal, and the steps each parked robot spends more than 0.1 away from its goal.
# Render the episodes first (stop 34's planner: --small-plan-candidates 1), then run it:
#   for m in madbp expert; do for s in $(seq 1000 1199); do build/madbp render --method $m --scenario parked \
#     --map obstacles --agents 4 --seed $s $([ $m = madbp ] && echo --small-plan-candidates 1) --out DIR/$m-$s.svg; done; done
#   python3 docs/diagnostics/parked_phases.py DIR 1000 1199
import math
import re
import statistics
import sys

PX, TOP = 200, 24  # the SVG's pixels per world unit and top margin (render's defaults)


def load(path):
    text = open(path).read()
    paths = []
    for pts in re.findall(r'<polyline[^>]*points="([^"]*)"', text):
        paths.append([(float(x) / PX, (float(y) - TOP) / PX) for x, y in (p.split(",") for p in pts.split())])
    found = re.search(r"success in (\d+) steps", text)
    return paths, int(found.group(1)) if found else None


def phases(paths, steps):
    goal = [p[-1] for p in paths]
    dist = [[math.dist(q, goal[i]) for q in p] for i, p in enumerate(paths)]
    return {
        "steps": steps,
        "last traveller within 0.3": max(next(k for k, d in enumerate(dist[i]) if d < 0.3) for i in (0, 1)),
        "parked 2 away": sum(d > 0.1 for d in dist[2]),
        "parked 3 away": sum(d > 0.1 for d in dist[3]),
    }


directory, first, last = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rows = {}
for method in ("madbp", "expert"):
    rows[method] = []
    for seed in range(first, last + 1):
        paths, steps = load(f"{directory}/{method}-{seed}.svg")
        if steps is not None:
            rows[method].append(phases(paths, steps))
print("mean over successful episodes", *rows)
for key in rows["madbp"][0]:
    print(key, *(round(statistics.mean(r[key] for r in rows[m]), 2) for m in rows))
