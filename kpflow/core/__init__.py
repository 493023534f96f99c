"""The contracts every layer above builds on, importing nothing of kpflow above the geometry and the trajectory:

* :mod:`.policy`: the :class:`~.policy.Policy` protocol, the :class:`~.policy.PolicyLayout` a task declares to its
  policies, and :class:`~.policy.ClosedLoop` (the observation history and action queue);
* :mod:`.phases` and :mod:`.symmetry`: a layout's phases (which object the transport follows before and after a
  grasp) and symmetries (relabellings of its keypoints that leave the task as it was);
* :mod:`.task`: the task contract (:class:`~.task.Task`, :class:`~.task.GymTask`, scenes, trial results);
* :mod:`.rollout`: the one closed-loop episode loop.

Tasks (``kpflow/tasks/``) implement them, policies (``kpflow/policies/``) act through them.
"""
