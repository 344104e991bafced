"""The DOLFINx layer: Lagrangian -> forms, integrators and the one time loop, recording and
state maps, intrusive projection, the gray-box nonlinearity, streaming POD, VTX output."""
