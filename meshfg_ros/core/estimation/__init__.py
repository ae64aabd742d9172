"""The factor graph and its MAP estimate: noise models, robust kernels, the factors (physics prior,
point-to-surface, temporal), the graph over the sliding window, the weights learnt from the data,
the published share of the correction, the covariance, and the estimator that runs an update."""
