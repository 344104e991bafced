"""CI: the main job's headline numbers (results/beam/metrics.json of `make demo`) within
stated bounds. Each bound has a factor >= 2 of margin over the figure measured when it was set
(README, "Latest measured figures"), so rounding on another machine cannot flip it, while a
regression of the method (a plateau, a blow-up, a drifting FOM) does."""

import json
import sys

BOUNDS = [
    # (basis, method, r, key, bound, measured when set)
    ("euclidean-block", "lopinf", 20, "test_error", 2.5e-3, 1.1e-3),
    ("euclidean-block", "lopinf_del", 20, "test_error", 2.0e-3, 8.0e-4),
    ("mass-orthonormal", "lopinf", 20, "test_error", 1.0e-5, 4.8e-6),
    ("mass-orthonormal", "lopinf_del", 20, "test_error", 2.0e-6, 8.5e-7),
    ("mass-orthonormal", "intrusive", 20, "test_error", 2.0e-6, 8.5e-7),
    ("mass-orthonormal", "lopinf", 20, "max_energy_error", 1.0e-7, 1.1e-8),
]


def main(path):
    m = json.loads(open(path).read())
    failures = []

    def check(name, value, bound):
        ok = value <= bound
        print(f"  {'ok ' if ok else 'BAD'} {name:55s} {value:10.3e} <= {bound:.1e}")
        if not ok:
            failures.append(name)

    print(f"demo metrics ({path}): scene {m['scene']}, quick={m['quick']}, "
          f"{len(m['roms'])} ROM rows")
    if m["scene"] != "beam" or m["quick"] or m["t_end"] < 0.18:
        sys.exit("the metrics are not those of the full beam demo (`make demo`)")
    check("FOM relative energy drift to t_end", m["fom_energy_drift"], 1e-9)
    rows = {(x["basis"], x["method"], x["r"]): x for x in m["roms"]}
    for basis, method, r, key, bound, _ in BOUNDS:
        row = rows.get((basis, method, r))
        if row is None:
            failures.append(f"missing row {basis}/{method}/r={r}")
            continue
        check(f"{basis} {method} r={r} {key}", row[key], bound)
    unstable = [(x["basis"], x["method"], x["r"]) for x in m["roms"]
                if x["method"].startswith("lopinf") and not x["stable"]]
    print(f"  {'ok ' if not unstable else 'BAD'} every L-OpInf ROM stable to t_energy "
          f"({sum(x['method'].startswith('lopinf') for x in m['roms'])} rows)")
    if unstable:
        failures.append(f"unstable L-OpInf ROMs {unstable}")
    if failures:
        sys.exit(f"demo metrics check FAILED: {failures}")
    print("demo metrics check passed")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "results/beam/metrics.json")
