"""Geometry of the tetrahedral mesh and its surface: the mesh and its quality checks, closest
points on the surface, topology changes by cuts, and distance queries against an estimate."""
