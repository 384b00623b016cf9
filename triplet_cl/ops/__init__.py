"""Host side of every kernel pair: validating wrappers around ``kernels_cl/<op>.cl``."""
