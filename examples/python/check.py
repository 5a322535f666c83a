#!/usr/bin/env python3
"""check.py - numpy against C++ on the same files (tests/consumer/check.sh runs it).

    python3 examples/python/check.py REF MODEL [LAYER] [DATASET]

REF is the built examples/python/madbp_ref.cpp. Checks that
  1. LAYER (default aap.mlp1, a madbp::Linear of MODEL) computed in numpy from the checkpoint,
     x @ W + b, matches the C++ layer's output on the same input (float32 products summed in a
     different order: compared to 1e-5 relative to the output's scale; the error is printed);
  2. DATASET (a `madbp collect` file), read by madbp_io.read_demos, holds exactly what the C++
     load_demos reads: every count, flag and value, bit for bit.
Prints one line per check; exits 1 when one fails.
"""
import json
import os
import subprocess
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from madbp_io import linear, read_demos, read_safetensors  # noqa: E402


def ref(*args):
    return json.loads(subprocess.run(list(args), check=True, capture_output=True, text=True).stdout)


def check_layer(ref_bin, model, layer):
    got = ref(ref_bin, "layer", model, layer)
    tensors, _ = read_safetensors(model)
    x = np.array(got["x"], dtype=np.float32)          # (N, in), the C++ input
    y_cpp = np.array(got["y"], dtype=np.float32)      # (N, out)
    y_np = linear(x, tensors, layer)                  # float32, numpy's order of summation
    y_64 = linear(x.astype(np.float64), {k: v.astype(np.float64) for k, v in tensors.items()}, layer)
    scale = float(np.abs(y_64).max())
    err_cpp = float(np.abs(y_cpp - y_64).max()) / scale
    err_np = float(np.abs(y_np - y_64).max()) / scale
    diff = float(np.abs(y_cpp - y_np).max())
    ok = y_cpp.shape == y_np.shape and err_cpp < 1e-5
    print(f"{'ok' if ok else 'FAILED'}: layer {layer} {x.shape[1]}->{y_cpp.shape[1]} on {x.shape[0]} inputs: "
          f"max |C++ - numpy float32| = {diff:.3g}; relative to float64: C++ {err_cpp:.3g}, numpy {err_np:.3g} "
          f"(max |y| = {scale:.3g})")
    return ok


def check_demos(ref_bin, path):
    want = ref(ref_bin, "demos", path)
    got = read_demos(path)
    problems = []
    if got["demonstrator"] != want["demonstrator"]:
        problems.append("demonstrator")
    if len(got["episodes"]) != len(want["episodes"]):
        problems.append(f"episode count {len(got['episodes'])} != {len(want['episodes'])}")
    for i, (g, w) in enumerate(zip(got["episodes"], want["episodes"])):
        for key in ("map_name", "half_size", "agents", "steps", "success"):
            if g[key] != w[key]:
                problems.append(f"episode {i}: {key} {g[key]!r} != {w[key]!r}")
        for key, dtype in (("discs", np.float64), ("boxes", np.float64), ("goals", np.float32),
                           ("pos", np.float32), ("vel", np.float32), ("act", np.float32)):
            a = g[key].reshape(-1)
            b = np.array(w[key], dtype=dtype).reshape(-1)
            if a.shape != b.shape or not np.array_equal(a, b):
                problems.append(f"episode {i}: {key} differs")
    n = len(got["episodes"])
    values = sum(e["pos"].size + e["vel"].size + e["act"].size + e["goals"].size for e in got["episodes"])
    print(f"{'ok' if not problems else 'FAILED'}: dataset {os.path.basename(path)}: {n} episodes, "
          f"{values} float32 values identical to C++ load_demos" + "".join("\n  " + p for p in problems[:10]))
    return not problems


def main(argv):
    if len(argv) < 3:
        print(__doc__)
        return 2
    ref_bin, model = argv[1], argv[2]
    layer = argv[3] if len(argv) > 3 else "aap.mlp1"
    ok = check_layer(ref_bin, model, layer)
    if len(argv) > 4:
        ok = check_demos(ref_bin, argv[4]) and ok
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
