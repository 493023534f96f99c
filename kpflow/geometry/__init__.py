"""Geometry below every map: the one rigid / similarity / affine fit (:mod:`.alignment`), rotations and their
representations (:mod:`.rotations`: the polar factor, 6-D and quaternions) and planar angles (:mod:`.angles`)."""
