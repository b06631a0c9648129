"""numba kernels: the compiled ones the package ships (:mod:`.shipped`, built by :mod:`.build`) and the
first-run warm-ups that compile them off the critical path where those do not fit (:mod:`.warmup`)."""
