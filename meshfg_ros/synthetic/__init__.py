"""Synthetic scenes whose ground truth comes from a model independent of the estimator's.

`hyperelastic`: static equilibrium of a heterogeneous compressible neo-Hookean solid
(scikit-fem assembly) under fixed vertices, body forces and a sticky rigid sphere tool.
`mismatch_scenes`: four scenes built on it (slab with an inclusion, tilted dome, liver under a
tilting table, kidney drag), registered in `core.scenarios`.
"""
