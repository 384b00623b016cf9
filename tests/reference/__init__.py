"""numpy references of the OpenCL ops (one module per op family)."""
