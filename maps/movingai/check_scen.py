#!/usr/bin/env python3
"""Check MovingAI MAPF scenario files (.scen) against their maps.

usage: python3 maps/movingai/check_scen.py [--sample N] SCEN [SCEN ...]

For each scenario file (looked up next to it, then in maps/movingai and maps/movingai/acceptance):
  * the first line is `version 1` and every row has 9 tab-separated fields
    (bucket, map name, width, height, start x, start y, goal x, goal y, optimal length;
    x = column, y = row, 0-based);
  * every row names the map file and its width and height equal the map's header;
  * every start and goal cell is passable ('.', 'G', 'S'; '@', 'O', 'T', 'W' are blocked);
  * the optimal length of every row (or of N rows spread over the file with --sample N)
    equals a shortest path computed here, to 1e-6, under each of three move models:
      octile          8 directions, diagonal sqrt(2), a diagonal needs both orthogonal
                      neighbours passable (no corner cutting, as MovingAI);
      octile-cut      8 directions, diagonal sqrt(2), a diagonal needs only its target;
      4-connected     unit moves up, down, left, right;
    the model that reproduces every checked row is reported;
  * the bucket equals floor(optimal length / 4);
  * the row count, and whether the starts (and the goals) are pairwise distinct.
Prints one summary line per file and exits 1 when any check fails.
"""
import hashlib
import heapq
import math
import os
import sys

PASSABLE = set(".GS")
BLOCKED = set("@OTW")
SQRT2 = math.sqrt(2.0)


def read_map(path):
    with open(path) as f:
        lines = f.read().split("\n")
    assert lines[0].strip() == "type octile", f"{path}: first line {lines[0]!r}"
    h = int(lines[1].split()[1]) if lines[1].startswith("height") else None
    w = int(lines[2].split()[1]) if lines[2].startswith("width") else None
    assert h and w and lines[3].strip() == "map", f"{path}: bad header"
    grid = lines[4:4 + h]
    assert len(grid) == h and all(len(r) == w for r in grid), f"{path}: grid is not {h} x {w}"
    chars = set("".join(grid))
    assert chars <= PASSABLE | BLOCKED, f"{path}: unknown cells {chars - PASSABLE - BLOCKED}"
    free = [[c in PASSABLE for c in r] for r in grid]
    return w, h, free, chars


def dijkstra(free, w, h, sx, sy, model):
    """Distances from (sx, sy) to every cell under a move model."""
    INF = float("inf")
    dist = [[INF] * w for _ in range(h)]
    dist[sy][sx] = 0.0
    pq = [(0.0, sx, sy)]
    steps = [(1, 0), (-1, 0), (0, 1), (0, -1)]
    diag = [(1, 1), (1, -1), (-1, 1), (-1, -1)] if model != "4-connected" else []
    while pq:
        d, x, y = heapq.heappop(pq)
        if d > dist[y][x]:
            continue
        for dx, dy in steps:
            nx, ny = x + dx, y + dy
            if 0 <= nx < w and 0 <= ny < h and free[ny][nx] and d + 1.0 < dist[ny][nx]:
                dist[ny][nx] = d + 1.0
                heapq.heappush(pq, (d + 1.0, nx, ny))
        for dx, dy in diag:
            nx, ny = x + dx, y + dy
            if not (0 <= nx < w and 0 <= ny < h and free[ny][nx]):
                continue
            if model == "octile" and not (free[y][nx] and free[ny][x]):
                continue
            nd = d + SQRT2
            if nd < dist[ny][nx]:
                dist[ny][nx] = nd
                heapq.heappush(pq, (nd, nx, ny))
    return dist


def find_map(scen_path, name):
    here = os.path.dirname(os.path.abspath(scen_path))
    root = os.path.dirname(os.path.abspath(__file__))
    for d in (here, os.path.dirname(here), root, os.path.join(root, "acceptance")):
        p = os.path.join(d, name)
        if os.path.exists(p):
            return p
    return None


def check(scen_path, sample):
    errors = []
    with open(scen_path, "rb") as f:
        raw = f.read()
    sha = hashlib.sha256(raw).hexdigest()
    if b"\r" in raw:
        errors.append("carriage returns in file")
    lines = raw.decode("ascii").split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    else:
        errors.append("no newline at end of file")
    if not lines or lines[0] != "version 1":
        errors.append(f"first line {lines[0] if lines else ''!r}, not 'version 1'")
    rows = []
    for i, line in enumerate(lines[1:], start=2):
        f = line.split("\t")
        if len(f) != 9:
            errors.append(f"line {i}: {len(f)} fields")
            continue
        rows.append((i, int(f[0]), f[1], int(f[2]), int(f[3]), int(f[4]), int(f[5]),
                     int(f[6]), int(f[7]), float(f[8])))
    names = {r[2] for r in rows}
    if len(names) != 1:
        errors.append(f"map names {sorted(names)}")
    name = sorted(names)[0]
    expected = os.path.basename(scen_path).rsplit("-", 2)[0] + ".map"
    if name != expected:
        errors.append(f"rows name {name}, file name says {expected}")
    mpath = find_map(scen_path, name)
    if mpath is None:
        errors.append(f"map {name} not found")
        return sha, len(rows), None, errors
    w, h, free, chars = read_map(mpath)
    for (i, b, _, rw, rh, sx, sy, gx, gy, L) in rows:
        if (rw, rh) != (w, h):
            errors.append(f"line {i}: size {rw} x {rh}, map is {w} x {h}")
        for (x, y, what) in ((sx, sy, "start"), (gx, gy, "goal")):
            if not (0 <= x < w and 0 <= y < h) or not free[y][x]:
                errors.append(f"line {i}: {what} ({x},{y}) not a passable cell")
        if b != math.floor(L / 4.0):
            errors.append(f"line {i}: bucket {b}, floor(length/4) = {math.floor(L / 4.0)}")
    starts = {(r[5], r[6]) for r in rows}
    goals = {(r[7], r[8]) for r in rows}
    if sample and sample < len(rows):
        step = len(rows) / sample
        checked = [rows[int(k * step)] for k in range(sample)]
    else:
        checked = rows
    models = {}
    for model in ("octile", "octile-cut", "4-connected"):
        cache = {}
        bad = 0
        worst = 0.0
        for (i, b, _, _, _, sx, sy, gx, gy, L) in checked:
            if (sx, sy) not in cache:
                cache[(sx, sy)] = dijkstra(free, w, h, sx, sy, model)
            d = cache[(sx, sy)][gy][gx]
            err = abs(d - L)
            worst = max(worst, err)
            if err > 1e-6:
                bad += 1
        models[model] = (bad, worst)
    ok_models = [m for m, (bad, _) in models.items() if bad == 0]
    if not ok_models:
        errors.append("no move model reproduces the optimal lengths: " +
                      ", ".join(f"{m} {bad} rows off" for m, (bad, _) in models.items()))
    info = {
        "map": os.path.relpath(mpath),
        "map_chars": "".join(sorted(chars)),
        "checked": len(checked),
        "models": models,
        "ok_models": ok_models,
        "distinct_starts": len(starts) == len(rows),
        "distinct_goals": len(goals) == len(rows),
    }
    return sha, len(rows), info, errors


def main(argv):
    sample = 0
    files = []
    it = iter(argv)
    for a in it:
        if a == "--sample":
            sample = int(next(it))
        else:
            files.append(a)
    if not files:
        print(__doc__)
        return 2
    failed = False
    for path in files:
        sha, n, info, errors = check(path, sample)
        print(f"{path}: {n} rows, sha256 {sha}")
        if info:
            print(f"  map {info['map']} (cells {info['map_chars']!r}); lengths checked on "
                  f"{info['checked']} rows; distinct starts {info['distinct_starts']}, "
                  f"distinct goals {info['distinct_goals']}")
            for m, (bad, worst) in info["models"].items():
                print(f"  {m:12s} {bad:5d} rows off, largest difference {worst:.3g}")
        for e in errors[:20]:
            print(f"  FAIL {e}")
        if len(errors) > 20:
            print(f"  FAIL ... {len(errors) - 20} more")
        print(f"  {'OK' if not errors else 'FAILED'}")
        failed |= bool(errors)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
