"""Off-screen renders and figures (pyvista, matplotlib: the ``viz`` extra)."""
