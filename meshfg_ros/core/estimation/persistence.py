"""How much of the factor graph's correction to the simulation to keep: the share that persists.

Each update corrects its prediction by c_t = X_t - Xhat_t (the newest state's optimum minus the
simulator's prediction). Model it as a systematic part s, which the simulation gets wrong from one
update to the next (a missed load, a stiffer inclusion, a tilted contact), plus a part n_t that is
new each time (the cloud's noise and leaks fitted through the prior):

    c_t = s + n_t,   E[c_t . c_t-1] = |s|^2,   E[(|c_t|^2 + |c_t-1|^2) / 2] = |s|^2 + E|n|^2.

Their ratio, summed over the recent updates,

    alpha = clip(sum c_t . c_t-1 / sum (|c_t|^2 + |c_t-1|^2) / 2, 0, 1),

is the share of a correction's energy that persists, and alpha c_t is the linear least-squares
(Wiener) estimate of s from c_t. The estimator publishes Xhat_t + alpha c_t. On a scene whose
simulation errs only where the camera cannot see it (a shear along the faces it sees flat on),
the corrections are noise from one update to the next and alpha stays at 0.3 or below (over the
accuracy suite's 15 steps): the estimate stays near the simulation instead of adding the noise
to it. Where the simulation misses
something systematic, consecutive corrections agree and alpha goes to 0.6-0.9 within a few
updates.

The sums forget: each update weighs the earlier terms by 1 - 1 / HORIZON, so after a change of
regime (a new load, the tool moving on to tissue the model fits differently) alpha follows
within about HORIZON updates instead of being held by the whole history; over sequences
shorter than HORIZON it is close to the plain sums.

The first update has no pair to judge by; alpha is 0 there, so its estimate is the prediction.
Updates without a prediction (degraded: the copy-forward stands in, and the correction is the
tool's motion, not the simulator's error) or without a cloud neither use nor teach alpha.
docs/design-notes.md ("Correction persistence") has the accuracy suite's figures.
"""

from __future__ import annotations

import numpy as np

__all__ = ["HORIZON", "CorrectionPersistence"]

# Updates over which the sums forget (20 s at a 1 Hz camera). Longer holds alpha steadier on
# noise (its spread is about 1 / sqrt(HORIZON * the correction's effective dimension)), shorter
# follows a change sooner.
HORIZON = 20
_KEEP = 1.0 - 1.0 / HORIZON


class CorrectionPersistence:
    """The running persistence share alpha of the corrections (see the module doc).

    Immutable in effect: `observe` replaces the arrays and numbers it holds instead of changing
    them in place, so a copy of its attributes restores it (the estimator undoes a failed update so).
    """

    def __init__(self) -> None:
        self.previous: np.ndarray | None = None  # the last observed correction, flattened
        self.products = 0.0   # forgetting sum of c_t . c_t-1
        self.energies = 0.0   # forgetting sum of (|c_t|^2 + |c_t-1|^2) / 2

    def observe(self, correction: np.ndarray) -> float:
        """Take the update's correction (any shape; the same each time) and return alpha for it."""
        correction = np.asarray(correction, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(correction)):
            raise ValueError("the correction contains non-finite values")
        previous = self.previous
        if previous is not None:
            if previous.shape != correction.shape:
                raise ValueError(f"a correction of {correction.size} values after one of {previous.size}")
            self.products = _KEEP * self.products + float(correction @ previous)
            self.energies = _KEEP * self.energies + 0.5 * float(correction @ correction + previous @ previous)
        self.previous = correction.copy()
        return float(np.clip(self.products / self.energies, 0.0, 1.0)) if self.energies > 0.0 else 0.0
