"""Policies: map an observation (and keypoints) to actions."""
