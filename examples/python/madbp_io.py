#!/usr/bin/env python3
"""madbp_io.py - read madbp's checkpoints and datasets with numpy alone (Debian: python3-numpy).

    from madbp_io import read_safetensors, read_demos, linear
    tensors, meta = read_safetensors("models/madbp-default.safetensors")
    w, b = tensors["aap.mlp1.weight"], tensors["aap.mlp1.bias"]     # (in, out), (out,)
    y = linear(x, tensors, "aap.mlp1")                               # x (N, in) -> (N, out)
    demos = read_demos("build/demos.bin")    # {"demonstrator": str, "episodes": [dict, ...]}

    python3 examples/python/madbp_io.py FILE    # prints what FILE holds

Formats (docs/formats.md):
  checkpoint  safetensors: u64 little-endian N; N bytes of JSON {name: {"dtype": "F32", "shape":
              [..], "data_offsets": [begin, end]}, "__metadata__": {key: value}}; then the
              payload of little-endian float32. Shapes are row-major (numpy order): Linear's
              weight is listed (in, out), so y = x @ W + b.
  dataset     "MADBPDS1", u32 version 1, string demonstrator, u32 episodes, then per episode:
              string map_name, f64 half_size, u32 discs + (f64 cx, cy, r) each, u32 boxes +
              (f64 x0, y0, x1, y1) each, u32 agents, u32 steps, u8 success, then float32 pairs:
              goals (agents), positions and velocities (steps + 1, agents), actions (steps,
              agents). A string is u32 length + bytes.
Both readers check sizes and raise ValueError naming the file and the field, as the C++ readers do.
"""
import json
import struct
import sys

import numpy as np

__all__ = ["read_safetensors", "read_demos", "linear"]


# ---------------------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------------------
def read_safetensors(path):
    """Returns ({name: float32 array of the listed shape}, {metadata key: value}), tensors in file order."""
    with open(path, "rb") as f:
        data = f.read()
    if len(data) < 8:
        raise ValueError(f"{path}: header size: file is shorter than 8 bytes")
    (n,) = struct.unpack_from("<Q", data, 0)
    if n > len(data) - 8:
        raise ValueError(f"{path}: header size: {n} bytes do not fit the file ({len(data)} bytes)")
    header = json.loads(data[8:8 + n].decode("utf-8"))
    meta = header.pop("__metadata__", {})
    payload = memoryview(data)[8 + n:]
    tensors = {}
    for name, info in sorted(header.items(), key=lambda kv: kv[1]["data_offsets"][0]):
        if info["dtype"] != "F32":
            raise ValueError(f"{path}: tensor '{name}': dtype {info['dtype']} (madbp writes F32 only)")
        begin, end = info["data_offsets"]
        shape = tuple(int(d) for d in info["shape"])
        if not 0 <= begin <= end <= len(payload) or (end - begin) != 4 * int(np.prod(shape, dtype=np.int64)):
            raise ValueError(f"{path}: tensor '{name}': data_offsets {begin}, {end} do not match shape {list(shape)}")
        tensors[name] = np.frombuffer(payload[begin:end], dtype="<f4").reshape(shape)
    return tensors, meta


def linear(x, tensors, name):
    """madbp::Linear named `name` on x (N, in): x @ W + b with W listed (in, out)."""
    y = x @ tensors[name + ".weight"]
    bias = tensors.get(name + ".bias")
    return y if bias is None else y + bias


# ---------------------------------------------------------------------------------------------
# Datasets (madbp collect)
# ---------------------------------------------------------------------------------------------
class _Reader:
    def __init__(self, data, path):
        self.data, self.pos, self.path = data, 0, path

    def fail(self, what):
        raise ValueError(f"{self.path}: {what}")

    def take(self, size, field):
        if self.pos + size > len(self.data):
            self.fail(f"file ends inside '{field}' (truncated)")
        view = self.data[self.pos:self.pos + size]
        self.pos += size
        return view

    def get(self, fmt, field):
        return struct.unpack("<" + fmt, self.take(struct.calcsize("<" + fmt), field))[0]

    def string(self, field):
        return bytes(self.take(self.get("I", field), field)).decode("utf-8")

    def array(self, dtype, shape, field):
        count = int(np.prod(shape, dtype=np.int64))
        return np.frombuffer(self.take(count * np.dtype(dtype).itemsize, field), dtype=dtype).reshape(shape)


def read_demos(path):
    """Returns {"demonstrator": str, "episodes": [episode, ...]}; an episode is a dict with map_name,
    half_size, discs (k, 3) [cx, cy, r], boxes (k, 4) [x0, y0, x1, y1], agents, steps, success,
    goals (agents, 2), pos and vel (steps + 1, agents, 2), act (steps, agents, 2), float32 arrays."""
    with open(path, "rb") as f:
        r = _Reader(memoryview(f.read()), path)
    if bytes(r.take(8, "magic")) != b"MADBPDS1":
        r.fail("not a madbp dataset (magic 'MADBPDS1' missing)")
    version = r.get("I", "version")
    if version != 1:
        r.fail(f"dataset version {version} is not supported (expected 1)")
    out = {"demonstrator": r.string("demonstrator"), "episodes": []}
    for _ in range(r.get("I", "episode count")):
        e = {"map_name": r.string("map_name"), "half_size": r.get("d", "half_size")}
        e["discs"] = r.array("<f8", (r.get("I", "discs"), 3), "discs")
        e["boxes"] = r.array("<f8", (r.get("I", "boxes"), 4), "boxes")
        agents, steps = r.get("I", "agents"), r.get("I", "steps")
        e.update(agents=agents, steps=steps, success=r.get("B", "success") != 0)
        e["goals"] = r.array("<f4", (agents, 2), "goals")
        e["pos"] = r.array("<f4", (steps + 1, agents, 2), "pos")
        e["vel"] = r.array("<f4", (steps + 1, agents, 2), "vel")
        e["act"] = r.array("<f4", (steps, agents, 2), "act")
        out["episodes"].append(e)
    if r.pos != len(r.data):
        r.fail(f"{len(r.data) - r.pos} trailing bytes after the last episode")
    return out


# ---------------------------------------------------------------------------------------------
def main(argv):
    if len(argv) != 2 or argv[1] in ("-h", "--help"):
        print("usage: madbp_io.py FILE   (a .safetensors checkpoint or a madbp collect dataset)")
        return 2
    path = argv[1]
    with open(path, "rb") as f:
        magic = f.read(8)
    if magic == b"MADBPDS1":
        d = read_demos(path)
        eps = d["episodes"]
        print(f"{path}: dataset of {len(eps)} episodes, demonstrator {d['demonstrator']}")
        for i, e in enumerate(eps[:10]):
            print(f"  {i}: {e['map_name']:9s} agents {e['agents']}  steps {e['steps']:3d}  success {int(e['success'])}"
                  f"  discs {len(e['discs'])}  boxes {len(e['boxes'])}")
        if len(eps) > 10:
            print(f"  ... {len(eps) - 10} more")
    else:
        tensors, meta = read_safetensors(path)
        count = sum(t.size for name, t in tensors.items() if not name.startswith("optim."))
        print(f"{path}: {len(tensors)} tensors, {count} parameters")
        for key in sorted(meta):
            print(f"  {key} = {meta[key]}")
        for name, t in tensors.items():
            print(f"  {name:40s} {list(t.shape)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
