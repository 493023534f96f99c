"""kpflow: generalise robot skills with sparse semantic keypoints.

Fit a smooth map phi from the keypoints of a demonstration's scene to those of a new scene
(:mod:`kpflow.maps`) and push the demonstration through it (:mod:`kpflow.transport`). Importing kpflow registers
its Gymnasium ids and the config resolvers ``${release:NAME}`` and ``${kpflow_data:NAME}``; :func:`load_policy`
loads a trained K-CFM for deployment, from a path or a released checkpoint's name (``release:NAME``,
:mod:`kpflow.utils.releases`).
"""

from importlib.metadata import version

from kpflow.tasks.pusht.registration import register_envs
from kpflow.utils.data_dir import register_resolver as register_data_resolver
from kpflow.utils.releases import register_resolver

__version__ = version("kpflow")  # pyproject.toml's, the one place it is written

register_envs()  # gymnasium.make("kpflow/PushT-v0") and the split ids (kpflow/tasks/pusht/registration.py)
register_resolver()  # ${release:NAME} in any config value (kpflow/utils/releases.py)
register_data_resolver()  # ${kpflow_data:NAME}: where collected and imported data go (kpflow/utils/data_dir.py)


def load_policy(path, steps: int | None = None, execute: int | None = None):
    """A ready K-CFM policy (``reset(seed)``, ``act(obs) -> [execute, 2]``) from a Lightning checkpoint (a path, or
    ``release:NAME`` for a released one: ``kpflow.load_policy("release:pusht_standard_fast")``), on the CPU,
    sampling with ``steps`` network calls and returning ``execute`` actions (None: the checkpoint's own settings,
    :mod:`kpflow.policies.settings`).

    A checkpoint trained on a GPU loads too; a missing file raises ``FileNotFoundError`` and a corrupt one a
    ``ValueError`` naming the file. Wrap it in :class:`kpflow.policies.transported_kcfm.TransportedKCFMPolicy` for
    online transport, or in :class:`kpflow.policies.subgoal.SubgoalPolicy` to show it its goal within reach and turn.
    """
    from kpflow.policies.kcfm.policy import KCFMPolicy

    return KCFMPolicy.from_checkpoint(path, steps=steps, execute=execute)
