"""Transportation maps: one interface (:class:`TransportMap`), many families."""

from kpflow.maps.affine import AffineMap
from kpflow.maps.base import TransportMap
from kpflow.maps.ensemble import EnsembleMap
from kpflow.maps.flow import FlowMap
from kpflow.maps.gp import GPMap
from kpflow.maps.ilwr import ILWRMap
from kpflow.maps.learned import LearnedMap
from kpflow.maps.matching import MatchResult, match_keypoints
from kpflow.maps.mlp import MLPMap

__all__ = [
    "AffineMap",
    "EnsembleMap",
    "FlowMap",
    "GPMap",
    "ILWRMap",
    "LearnedMap",
    "MLPMap",
    "MatchResult",
    "TransportMap",
    "match_keypoints",
]
