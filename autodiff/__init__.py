"""The op graph: Function (forward/backward), Tape and gradcheck (installed as ``triplet_cl.autodiff``)."""
