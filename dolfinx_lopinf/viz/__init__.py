"""Off-screen renders and figures (pyvista, matplotlib: the ``viz`` extra), e.g.

    grid = lo.viz.grid_on_root(V)            # rank 0: the mesh, point i = dof block i of V
    lo.viz.deformed_side_by_side("shape.png", grid, [{"FOM": d_fom, "ROM": d_rom}], magnify=50)

(``d_*``: (n_points, 3) displacements in V's dof order - ``state_map.to_dofs(state)`` reshaped
to (-1, bs), padded to three columns.)

Each function writes one PNG (or GIF) and returns its path; pyvista and matplotlib are
imported when a figure is drawn, never by ``import dolfinx_lopinf``.
"""

from .render import (animation, beam_shapes, curves, deformed_side_by_side, error_vs_parameter,
                     error_vs_r, grid_on_root, output_error_energy, scalar_fields, speed_vs_error,
                     wave_shapes)

__all__ = ["animation", "beam_shapes", "curves", "deformed_side_by_side", "error_vs_parameter",
           "error_vs_r", "grid_on_root", "output_error_energy", "scalar_fields", "speed_vs_error",
           "wave_shapes"]
