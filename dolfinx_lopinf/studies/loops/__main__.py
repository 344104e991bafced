"""python -m dolfinx_lopinf.studies.loops [--size quick|default] [--r 2,4,8] [--loops a,b]
[--verify] [--copies N] [--out results/loops]

For each user loop: record training and test data with lo.SnapshotRecorder, fit lo.fit with
today's defaults and print lo.fit's unseen-load error beside the intrusive ROM of the loop's
own scheme and the projection floor (study.py). ``--verify`` also runs the reference with the
full basis (r = n) against the loop at the chosen size. Writes OUT/metrics.json and the
recorded snapshots OUT/<loop>_{train,test[,free]}.npz (re-fit them with lo.Snapshots.load).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..harness import write_metrics
from . import study


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", choices=("quick", "default"), default="default")
    p.add_argument("--r", default="2,4,8")
    p.add_argument("--loops", default=",".join(study.LOOPS))
    p.add_argument("--verify", action="store_true", help="also check the reference at r = n")
    p.add_argument("--copies", type=int, default=1,
                   help="also fit N - 1 copies of each recording perturbed at 1e-15 (the choices "
                        "and errors should agree)")
    p.add_argument("--out", default="results/loops")
    args = p.parse_args(argv)
    rs = tuple(int(x) for x in args.r.split(","))
    if args.copies < 1:
        p.error("--copies must be >= 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in args.loops.split(","):
        t0 = time.perf_counter()
        res = study.run_loop(name, args.size, rs, save_to=out, copies=args.copies)
        if args.verify:
            res["verify_r_eq_n"] = study.verify(study.load_loop(name), args.size)
        res["study_seconds"] = time.perf_counter() - t0
        print(study.table(res))
        if args.verify:
            v = res["verify_r_eq_n"]
            print(f"  r = n = {v['n_free']}: reference vs loop  u {v['Q']:.1e}"
                  + "".join(f", {k.lower()} {v[k]:.1e}" for k in ("V", "A") if v[k] is not None))
        print(f"  ({res['study_seconds']:.1f} s in all)\n")
        results[name] = res
    metrics = {"study": "user_loops", "size": args.size, "r": list(rs),
               "errors": "relative Frobenius errors on the unseen test load; out = point output "
                         "(loop.OUTPUT), st = states; floor = ||Q - W W^T Q|| / ||Q|| in lo.fit's POD basis",
               "loops": results}
    path = write_metrics(out, metrics)
    print(f"wrote {path}")
    return metrics


if __name__ == "__main__":
    main()
