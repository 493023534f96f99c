"""What a policy takes and hands a robot is checked at its boundary: observations within reach of the training data,
finite actions only.

An observation far outside the data a K-CFM was trained on means nothing to it: every K-CFM policy refuses
coordinates farther outside the training keypoints' box than :data:`INPUT_MARGIN` times the box's extent on each side
(:meth:`~kpflow.policies.kcfm.KCFM.check_in_range`, which owns the statistics; configurable per policy as
``input_margin``, and by ``kpflow-serve input_margin=...``).

A trained network fed extreme (finite) observations, or with weights that overflow for some input, returns inf or
NaN targets, and a robot told to move to NaN does whatever its controller makes of it. Every K-CFM policy (plain,
transported, within reach and turn) and the policy server pass their actions through :func:`check_actions`, which
refuses them with a ``ValueError`` naming the policy and what was wrong instead of returning them.
"""

from __future__ import annotations

import numpy as np

#: The default ``input_margin``: 10 box extents on each side accept Push-T's 1024-px OOD workspaces (object_ood,
#: robot_ood) many times over and refuse the absurd (a keypoint at 1e300 px).
INPUT_MARGIN = 10.0


def check_actions(actions, policy: str) -> np.ndarray:
    """``actions`` as a float64 array if every value is finite; else ``ValueError`` naming ``policy``, how many values
    are NaN or inf and at which steps (rows)."""
    a = np.asarray(actions, dtype=np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        steps = np.nonzero(bad.reshape(len(a), -1).any(-1) if a.ndim > 1 else np.atleast_1d(bad))[0]
        raise ValueError(
            f"{policy} produced {int(bad.sum())} NaN or inf action value(s) of {a.size} (steps {steps[:10].tolist()}); "
            "refusing to return them"
        )
    return a
