"""A planar reaching task written as a user would write their own: one folder (this package) and one YAML
(``conf/task/reach.yaml``). See docs/tutorials/own-task.md."""

from .task import ReachEnv, ReachExpert, ReachTask

__all__ = ["ReachEnv", "ReachExpert", "ReachTask"]
