"""Correspondences for unordered keypoints: :func:`match_keypoints` with one registration method per file."""

from .base import UNMATCHED, MatchResult
from .match import METHODS, match_keypoints

__all__ = ["METHODS", "UNMATCHED", "MatchResult", "match_keypoints"]
