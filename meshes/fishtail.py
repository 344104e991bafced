"""Write the soft-robotic fishtail mesh (gmsh) to a .msh file.

    python meshes/fishtail.py [--size small|default|large | --lc METRES] [--out FILE.msh]

The geometry (hull, carbon beam, two chambers, physical groups) lives in the package:
:mod:`dolfinx_lopinf.scenes.fishtail_geometry`, which ``dolfinx_lopinf.scenes.fishtail``
meshes directly; this script only writes it to disk.
"""

from __future__ import annotations

import argparse

from dolfinx_lopinf.scenes.fishtail_geometry import SIZES, write_msh


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=sorted(SIZES), default="default")
    parser.add_argument("--lc", type=float, help="element size in metres (overrides --size)")
    parser.add_argument("--out", default="fishtail.msh")
    args = parser.parse_args(argv)
    nodes = write_msh(args.out, args.lc or SIZES[args.size], verbose=True)
    print(f"wrote {args.out}: {nodes} nodes (P1: {3 * nodes} displacement dofs)")


if __name__ == "__main__":
    main()
