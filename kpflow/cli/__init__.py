"""kpflow's commands, one Hydra entry point each, installed as console scripts (``kpflow-train``, ``kpflow-evaluate``,
``kpflow-collect``, ``kpflow-correct``, ``kpflow-generate``, ``kpflow-serve``, ``kpflow-release``,
``kpflow-teleop``, ``kpflow-verify``) and runnable as ``python -m kpflow.cli.<command>``. Every command reads its
config from ``kpflow/conf/<command>.yaml`` and takes Hydra overrides (``key=value``, ``group=option``,
``--config-dir DIR`` for a project's own config groups, ``--help`` for the composed config)."""

import os
import sys

# A console script's sys.path starts at its bin/ folder; put the working folder first, as ``python -m`` does, so that
# a project's own modules (a task's ``_target_``, a config group's classes) import from where the command runs.
if os.getcwd() not in sys.path:
    sys.path.insert(0, os.getcwd())
