"""What the tissue model misses, fitted to what the measurements see of each correction.

After each update the simulator learns from the estimate's correction of its prediction,
c = estimate - prediction: the unmodelled body load (core/physics/body_load.py) and the tissue's
compressibility (core/physics/poisson_ratio.py). Each is a few numbers p whose small-strain responses
R = dX/dp (one (N, 3) field per number) are known. They are fitted jointly, by weighted least
squares, to the normal components of c at the surface vertices:

    dp = argmin sum_v w_v (n_v . (R_v dp) - n_v . c_v)^2,    w_v = 1 / position_std_v^2

- Normal components: a point-to-surface factor measures the distance along the normal. The
  tangential and the hidden parts of a correction are the physics prior's extension of it
  through the very model being fitted; fitted as data they read noise as a change of the model
  (a sheared cube's corrections gave it a less compressible body, the opposite of its truth).
- Surface vertices weighted by the estimate's information about them (position_std, which the
  estimate message carries): a vertex the camera sees counts more than one the prior alone
  places.
- Jointly: a load and a compressibility both bend the visible surface; fitted one after the
  other, the second takes what the first left of the first's error for its own (fitted after
  the load, liver-push's ratio ran to 0.30, its truth's being 0.48).

Both are integrators: the next correction measures what they still miss.
docs/design-notes.md ("The airway over its steps") has the accuracy suite's figures.
"""

from __future__ import annotations

import numpy as np

from meshfg_ros.core.physics.body_load import BodyLoadEstimate
from meshfg_ros.core.geometry.mesh import TetMesh
from meshfg_ros.core.physics.poisson_ratio import PoissonRatioEstimate

__all__ = ["learn", "surface_fit"]


def learn(mesh: TetMesh, body_load: BodyLoadEstimate | None, poisson_ratio: PoissonRatioEstimate | None,
          predicted: np.ndarray, estimate: np.ndarray, position_std: np.ndarray) -> None:
    """Fit the increments of the body load and the Poisson ratio (those not None) to the
    correction `estimate` - `predicted` (both (N, 3)) and apply them (module docstring)."""
    responses = []
    if body_load is not None:
        responses.extend(body_load.responses())
    if poisson_ratio is not None:
        responses.append(poisson_ratio.sensitivity(predicted))
    if not responses:
        return
    increments = surface_fit(mesh, predicted, estimate - predicted, position_std, np.stack(responses))
    if body_load is not None:
        body_load.add(increments[:3])
    if poisson_ratio is not None:
        poisson_ratio.add(increments[-1])


def surface_fit(mesh: TetMesh, predicted: np.ndarray, correction: np.ndarray, position_std: np.ndarray,
                responses: np.ndarray) -> np.ndarray:
    """Coefficients (k,) of `responses` (k, N, 3) that best explain `correction` (N, 3) along the
    normals of the surface at `predicted` (N, 3), each surface vertex weighted by
    1 / `position_std`^2 (N,; a zero, negative or non-finite std leaves its vertex out). Zero
    where the weighted surface does not see a response: the system is solved in the least-norm
    sense (all zero without a weighted vertex)."""
    normals = mesh.vertex_normals(predicted)  # zero rows off the surface
    position_std = np.asarray(position_std, dtype=np.float64)
    weights = np.zeros(len(position_std))
    known = np.flatnonzero(np.isfinite(position_std) & (position_std > 0.0))
    weights[known] = 1.0 / position_std[known] ** 2
    along_responses = np.einsum("vi,kvi->vk", normals, responses)  # (N, k)
    along_correction = np.einsum("vi,vi->v", normals, correction)
    system = along_responses.T @ (weights[:, None] * along_responses)
    return np.linalg.lstsq(system, along_responses.T @ (weights * along_correction), rcond=None)[0]
