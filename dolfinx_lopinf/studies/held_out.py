"""The certified fit on held-out data: the benchmark's data kinds at seeds it does not use.

    python -m dolfinx_lopinf.studies.held_out [--seeds 0:26] [--conservative] [--out FILE.json]

For every kind (forced, rigid, mixed, short), r in {4, 6, 12, 20}, K in {3000, 10000} and
seed, :func:`dolfinx_lopinf.core.infer_mechanical` with the default solver - (Kh, Ch, Bh), or with
``--conservative`` (Kh, Bh) alone, one constrained block; prints how many fits each path
answered (symmetric or Lyapunov minimiser, interior point, its crossover, ADMM, barrier), the
uncertified ones, and the solve time per r (median and maximum of the best of 3 runs).
"""

from __future__ import annotations

import argparse
import json
import warnings

import numpy as np

from ..core import inference
from .benchmark import ACTIVE_KINDS, mechanical_data


def run(seeds, r_values=(4, 6, 12, 20), k_values=(3000, 10000), damping=True) -> list[dict]:
    rows = []
    for kind in ("forced", *ACTIVE_KINDS):
        for r in r_values:
            for K in k_values:
                for seed in seeds:
                    data = mechanical_data(kind, r, K, seed)
                    if not damping:
                        data = (data[0], None, data[2], data[3])
                    seconds = []
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        for _ in range(3):
                            c = inference.infer_mechanical(*data, eps=1e-8,
                                                           damping=damping).certificate
                            seconds.append(c["seconds"])
                    path = c["solver"] + ("+crossover" if c.get("ipm", {}).get("crossover") else "")
                    rows.append({"kind": kind, "r": r, "K": K, "seed": seed, "path": path,
                                 "converged": bool(c["converged"]), "gap": c.get("duality_gap"),
                                 "ms": 1e3 * min(seconds)})
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0:26", help="a:b, the seeds a..b-1")
    ap.add_argument("--conservative", action="store_true", help="fit (Kh, Bh) alone")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    a, b = (int(v) for v in args.seeds.split(":"))
    rows = run(range(a, b), damping=not args.conservative)
    paths = sorted({row["path"] for row in rows})
    print(f"{len(rows)} fits; paths: " + ", ".join(
        f"{p} {sum(row['path'] == p for row in rows)}" for p in paths))
    bad = [row for row in rows if not row["converged"]]
    print(f"uncertified: {len(bad)}", *[f"\n  {row}" for row in bad])
    for r in sorted({row["r"] for row in rows}):
        ms = [row["ms"] for row in rows if row["r"] == r]
        print(f"r = {r:2d}: solve median {np.median(ms):.2f} ms, max {max(ms):.2f} ms")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
