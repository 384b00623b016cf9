"""The ``triplet`` command line (installed as ``triplet_cl.cli``)."""
