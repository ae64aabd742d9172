"""The physics: the FEM stiffness, the simulator that predicts the next state from the previous
estimate and the tool pose, an external simulator's prediction as a prior, and what the model
learns from the estimates (body load, Poisson ratio)."""
