"""Soft-robotic fishtail geometry (gmsh OpenCASCADE), docs/method.md#fishtail.

Used by :mod:`dolfinx_lopinf.scenes.fishtail`; ``meshes/fishtail.py`` (in the source tree)
is the command-line script that writes it to a .msh file with :func:`write_msh`.

The tail points along +z from its clamped root (z = 0). A silicone hull is lofted through
three ellipses (x is the lateral, bending direction; y is the height):

    z = 0      semi-axes (0.025, 0.030) m
    z = 0.12   semi-axes (0.018, 0.026) m
    z = 0.24   semi-axes (0.003, 0.016) m

A carbon centre beam (1 mm x 1 mm section: a rod, so that the chambers bend the tail - a
2 mm x 20 mm plate was 100x stiffer in bending than the hull and the tail barely moved while
the chamber walls ballooned) runs along the axis from the root to its rear tip at
(0, 0, 0.21) - the point of interest. Two fluid chambers (10 x 24 x 85 mm boxes, z from 15
to 100 mm) sit either side of the beam, at 3 mm from it. The chambers are holes: their walls
carry the pressure load. The element size is lc in the hull, graded (distance field) down to
max(1.2 mm, 0.4 lc) at the beam (one element across the rod on the large mesh; the small
mesh's static tip deflection is 16 % below the 1.2 mm-graded one's, fine for tests). Physical groups:

    volumes   1 "hull", 2 "beam"
    surfaces  11 "chamber_left" (x < 0), 12 "chamber_right" (x > 0), 20 "root" (z = 0)
"""

from __future__ import annotations

#: element sizes: small (tests) 22,173 P2 dofs, default 46,224, large 795,405 (>= 779,232)
SIZES = {"small": 0.012, "default": 0.007, "large": 0.00195}
ELLIPSES = [(0.0, 0.025, 0.030), (0.12, 0.018, 0.026), (0.24, 0.003, 0.016)]
BEAM = dict(half_thickness=0.0005, half_height=0.0005, length=0.21)
CHAMBER = dict(gap=0.003, width=0.010, half_height=0.012, z0=0.015, z1=0.100)
TAGS = {"hull": 1, "beam": 2, "chamber_left": 11, "chamber_right": 12, "root": 20}


def build(lc: float, *, order: int = 1, verbose: bool = False):
    """Create the gmsh model (gmsh must be initialised by the caller) and mesh it.

    Args:
        lc: target element size in metres (the beam gets at most half of it).
        order: geometric order of the mesh.

    Returns:
        The ``gmsh.model`` module, ready for ``dolfinx.io.gmshio.model_to_mesh``.
    """
    import gmsh

    gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
    gmsh.model.add("fishtail")
    occ = gmsh.model.occ
    wires = []
    for z, a, b in ELLIPSES:
        # OCC wants the major radius first: put it along y (the height), minor along x
        curve = occ.addEllipse(0, 0, z, b, a, zAxis=[0, 0, 1], xAxis=[0, 1, 0])
        wires.append(occ.addCurveLoop([curve]))
    hull = occ.addThruSections(wires, makeSolid=True, makeRuled=False)[0][1]
    c = CHAMBER
    right = occ.addBox(c["gap"], -c["half_height"], c["z0"], c["width"], 2 * c["half_height"],
                       c["z1"] - c["z0"])
    left = occ.addBox(-c["gap"] - c["width"], -c["half_height"], c["z0"], c["width"],
                      2 * c["half_height"], c["z1"] - c["z0"])
    solid = occ.cut([(3, hull)], [(3, right), (3, left)])[0]
    bm = BEAM
    beam = occ.addBox(-bm["half_thickness"], -bm["half_height"], 0.0, 2 * bm["half_thickness"],
                      2 * bm["half_height"], bm["length"])
    occ.fragment(solid, [(3, beam)])
    occ.synchronize()

    volumes = gmsh.model.getEntities(3)
    beam_vols, hull_vols = [], []
    for dim, tag in volumes:
        xmin, ymin, zmin, xmax, ymax, zmax = gmsh.model.getBoundingBox(dim, tag)
        is_beam = (xmax - xmin) < 3 * bm["half_thickness"] and abs(zmax - bm["length"]) < 1e-6
        (beam_vols if is_beam else hull_vols).append(tag)
    if len(beam_vols) != 1 or not hull_vols:
        raise RuntimeError(f"unexpected fragments: beam {beam_vols}, hull {hull_vols}")
    gmsh.model.addPhysicalGroup(3, hull_vols, TAGS["hull"], "hull")
    gmsh.model.addPhysicalGroup(3, beam_vols, TAGS["beam"], "beam")

    left_walls, right_walls, root = [], [], []
    eps = 1e-6
    for dim, tag in gmsh.model.getEntities(2):
        xmin, ymin, zmin, xmax, ymax, zmax = gmsh.model.getBoundingBox(dim, tag)
        if zmax < eps:
            root.append(tag)
            continue
        inside_z = zmin > c["z0"] - eps and zmax < c["z1"] + eps
        inside_y = ymin > -c["half_height"] - eps and ymax < c["half_height"] + eps
        if inside_z and inside_y:
            if xmin > c["gap"] - eps and xmax < c["gap"] + c["width"] + eps:
                right_walls.append(tag)
            elif xmax < -c["gap"] + eps and xmin > -c["gap"] - c["width"] - eps:
                left_walls.append(tag)
    if len(left_walls) != 6 or len(right_walls) != 6:
        raise RuntimeError(f"expected 6 walls per chamber, got {len(left_walls)}, {len(right_walls)}")
    gmsh.model.addPhysicalGroup(2, left_walls, TAGS["chamber_left"], "chamber_left")
    gmsh.model.addPhysicalGroup(2, right_walls, TAGS["chamber_right"], "chamber_right")
    gmsh.model.addPhysicalGroup(2, root, TAGS["root"], "root")

    # element size: lc in the hull, graded down to the beam's thickness at the beam (one P2
    # element across it keeps its bending; distance-based so the refined zone stays thin)
    field = gmsh.model.mesh.field
    beam_surfaces = [s for _, s in gmsh.model.getBoundary([(3, beam_vols[0])], oriented=False)]
    dist = field.add("Distance")
    field.setNumbers(dist, "SurfacesList", beam_surfaces)
    field.setNumber(dist, "Sampling", 60)
    size_min = min(lc, max(2.4 * bm["half_thickness"], 0.4 * lc))
    thr = field.add("Threshold")
    field.setNumber(thr, "InField", dist)
    field.setNumber(thr, "SizeMin", size_min)
    field.setNumber(thr, "SizeMax", lc)
    field.setNumber(thr, "DistMin", 0.5 * size_min)
    field.setNumber(thr, "DistMax", 0.5 * size_min + 2.0 * lc)
    field.setAsBackgroundMesh(thr)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.Algorithm3D", 10)  # HXT, parallel and fast
    gmsh.model.mesh.generate(3)
    if order > 1:
        gmsh.model.mesh.setOrder(order)
    return gmsh.model


def write_msh(path, lc: float, *, verbose: bool = True) -> int:
    """Mesh the fishtail with element size lc (metres) and write it to ``path`` (.msh).

    Initialises and finalises gmsh itself. Returns the number of mesh nodes.
    """
    import gmsh

    gmsh.initialize()
    try:
        build(lc, verbose=verbose)
        gmsh.write(str(path))
        return len(gmsh.model.mesh.getNodes()[0])
    finally:
        gmsh.finalize()
