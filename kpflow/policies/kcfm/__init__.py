"""K-CFM, the keypoint-conditioned flow-matching policy: the Lightning module (:mod:`.model`), its processors
(:mod:`.frames`: goal and robot frames), sampling (:mod:`.sampling`), loss (:mod:`.losses`), networks
(:mod:`.networks`), generative objectives (:mod:`.objectives`) and the policy that runs it (:mod:`.policy`)."""

from .model import KCFM

__all__ = ["KCFM"]
