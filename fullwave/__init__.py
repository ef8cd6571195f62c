"""Full-wave (FDTD) simulation of the unrolled pipe wall: PipeSentry's independent check on its ray physics (docs/fullwave.md)."""
