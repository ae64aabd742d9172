"""Sparse linear algebra and optimisation: the window's linear system, its solvers (sparse Cholesky,
preconditioned conjugate gradients) and Levenberg-Marquardt. Knows nothing of meshes or factors."""
