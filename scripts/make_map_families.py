#!/usr/bin/env python3
"""Generated stand-ins for three MovingAI MAPF benchmark map families (issue 46).

The benchmark files room-64-64-8, random-64-64-10 and warehouse-10-20-10-2-2 could not be
fetched from this workplace, so this script writes maps of the same families, from a seed, in
the MovingAI .map format, named <family>-gen.map so they are never taken for the benchmark
files (maps/movingai/README.md says what each one is):

  room-64-64-8-gen.map            64 x 64: 8 x 8 rooms of 7 x 7 free cells, one-cell walls
                                  (rows and columns 7, 15, ..., 63); a random spanning tree of
                                  doors joins every room, and each other neighbouring pair gets
                                  a door with probability --extra-doors (loops, as in the
                                  benchmark's rooms); a door is one opened wall cell.
  random-64-64-10-gen.map         64 x 64: exactly 10 % of the cells (410) blocked at random; a
                                  draw that would cut the free cells in two is skipped, so the
                                  free cells form one component.
  warehouse-10-20-10-2-2-gen.map  170 x 84 (the size in the benchmark's scenario rows): 10
                                  columns x 20 rows of shelf blocks, each 10 cells long and 2
                                  deep, 2-cell aisles between them; a free band of 26 columns
                                  left and right (the stations' side) and 3 rows above and below.

Connectivity is the benchmark's octile moves without corner cutting, which joins the same cells
as 4-neighbour moves; every map is checked connected before it is written. Standard library
only. Usage: scripts/make_map_families.py [--seed S] [--out-dir DIR]
"""
import argparse
import os
import random
import sys
from collections import deque


def components(grid):
    """The free-cell components (4-neighbour moves) of grid[row][col] (True = blocked)."""
    h, w = len(grid), len(grid[0])
    seen = [[False] * w for _ in range(h)]
    out = []
    for r0 in range(h):
        for c0 in range(w):
            if grid[r0][c0] or seen[r0][c0]:
                continue
            seen[r0][c0] = True
            queue, cells = deque([(r0, c0)]), []
            while queue:
                r, c = queue.popleft()
                cells.append((r, c))
                for nr, nc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                    if 0 <= nr < h and 0 <= nc < w and not grid[nr][nc] and not seen[nr][nc]:
                        seen[nr][nc] = True
                        queue.append((nr, nc))
            out.append(cells)
    return out


def room_map(rng, extra_doors):
    side, room, rooms = 64, 7, 8
    grid = [[(r % (room + 1) == room) or (c % (room + 1) == room) for c in range(side)] for r in range(side)]
    # Neighbouring room pairs, as ((i, j), (i2, j2)) with room (i, j) at rows 8i.., columns 8j..
    pairs = [((i, j), (i, j + 1)) for i in range(rooms) for j in range(rooms - 1)]
    pairs += [((i, j), (i + 1, j)) for i in range(rooms - 1) for j in range(rooms)]
    rng.shuffle(pairs)
    parent = {(i, j): (i, j) for i in range(rooms) for j in range(rooms)}

    def root(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in pairs:
        joins = root(a) != root(b)  # a tree door (Kruskal on shuffled pairs) or an extra one
        if not joins and rng.random() >= extra_doors:
            continue
        parent[root(a)] = root(b)
        at = rng.randrange(room)  # the door's place along the shared wall
        if a[0] == b[0]:  # side by side: the wall column between them
            grid[a[0] * (room + 1) + at][a[1] * (room + 1) + room] = False
        else:  # one above the other: the wall row between them
            grid[a[0] * (room + 1) + room][a[1] * (room + 1) + at] = False
    return grid


def random_map(rng, fraction):
    side = 64
    grid = [[False] * side for _ in range(side)]
    target = round(fraction * side * side)
    cells = [(r, c) for r in range(side) for c in range(side)]
    rng.shuffle(cells)
    blocked = 0
    for r, c in cells:
        if blocked == target:
            break
        grid[r][c] = True
        if len(components(grid)) > 1:  # it would cut the free cells in two: skip it
            grid[r][c] = False
            continue
        blocked += 1
    if blocked != target:
        sys.exit("make_map_families: random map: could block only %d of %d cells" % (blocked, target))
    return grid


def warehouse_map():
    width, height = 170, 84
    cols, rows, length, depth, aisle, side_band, top_band = 10, 20, 10, 2, 2, 26, 3
    assert side_band * 2 + cols * length + (cols - 1) * aisle == width
    assert top_band * 2 + rows * depth + (rows - 1) * aisle == height
    grid = [[False] * width for _ in range(height)]
    for i in range(rows):
        for j in range(cols):
            r0, c0 = top_band + i * (depth + aisle), side_band + j * (length + aisle)
            for r in range(r0, r0 + depth):
                for c in range(c0, c0 + length):
                    grid[r][c] = True
    return grid


def write_map(path, grid):
    text = "type octile\nheight %d\nwidth %d\nmap\n" % (len(grid), len(grid[0]))
    text += "".join("".join("@" if b else "." for b in row) + "\n" for row in grid)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="ascii", newline="\n") as f:
        f.write(text)
    os.replace(tmp, path)  # atomic: a reader sees the old file or the whole new one


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out-dir", default=os.path.normpath(os.path.join(os.path.dirname(__file__), "..", "maps", "movingai")),
                   help="where the .map files go (default maps/movingai beside this script)")
    p.add_argument("--extra-doors", type=float, default=0.5, help="room map: chance of a door beyond the spanning tree (default 0.5)")
    a = p.parse_args()
    if not 0 <= a.extra_doors <= 1:
        p.error("--extra-doors: must be in [0, 1]")
    # One generator per map, each seeded from --seed and the map's name: a map does not change
    # when another one's recipe does.
    maps = {
        "room-64-64-8-gen": lambda: room_map(random.Random("room %d" % a.seed), a.extra_doors),
        "random-64-64-10-gen": lambda: random_map(random.Random("random %d" % a.seed), 0.10),
        "warehouse-10-20-10-2-2-gen": warehouse_map,
    }
    for name, make in maps.items():
        grid = make()
        parts = components(grid)
        if len(parts) != 1:
            sys.exit("make_map_families: %s: %d free components, expected 1" % (name, len(parts)))
        blocked = sum(map(sum, grid))
        path = os.path.join(a.out_dir, name + ".map")
        write_map(path, grid)
        print("%s: %d x %d, %d blocked cells (%.1f %%), %d free cells in one component" %
              (path, len(grid[0]), len(grid), blocked, 100.0 * blocked / (len(grid) * len(grid[0])), len(parts[0])))


if __name__ == "__main__":
    main()
