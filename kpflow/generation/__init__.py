"""Demonstration generation: one recorded demonstration carried segment by segment into new scenes
(:mod:`.segment_transport`: MimicGen's object-frame transform or a keypoint map), whole datasets generated per
variant and family, sharded and resumable (:mod:`.generate`, :mod:`.journal`), and written for robomimic
(:mod:`.robomimic_export`)."""
