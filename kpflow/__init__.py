"""kpflow: generalise robot skills with sparse semantic keypoints.

Fit a smooth map phi from the keypoints of a demonstration's scene to those of a new scene
(:mod:`kpflow.maps`) and push the demonstration through it (:mod:`kpflow.transport`).
"""

__version__ = "0.1.0"
