"""The DOLFINx layer: Lagrangian -> forms, integrators and the one time loop, recording and
state maps, intrusive projection, the gray-box nonlinearity, streaming POD, VTX output; the
affine parameter structure of a UFL Lagrangian (``affine``) and the FOM at any parameter
(``param_fom``)."""
