"""kpflow: generalise robot skills with sparse semantic keypoints.

Fit a smooth map phi from the keypoints of a demonstration's scene to those of a new scene
(:mod:`kpflow.maps`) and push the demonstration through it (:mod:`kpflow.transport`). Importing kpflow registers
its Gymnasium ids and the config resolvers ``${release:NAME}``, ``${kpflow_data:NAME}`` and ``${choice:GROUP}``; :func:`load_policy`
loads a trained policy for deployment as its checkpoint describes it, from a path or a released checkpoint's name (``release:NAME``,
:mod:`kpflow.utils.releases`).
"""

from importlib.metadata import version

from kpflow.tasks.pusht.registration import register_envs
from kpflow.utils.data_dir import register_resolver as register_data_resolver
from kpflow.utils.group_choice import register_resolver as register_choice_resolver
from kpflow.utils.releases import register_resolver

__version__ = version("kpflow")  # pyproject.toml's, the one place it is written

register_envs()  # gymnasium.make("kpflow/PushT-v0") and the split ids (kpflow/tasks/pusht/registration.py)
register_resolver()  # ${release:NAME} in any config value (kpflow/utils/releases.py)
register_data_resolver()  # ${kpflow_data:NAME}: where collected and imported data go (kpflow/utils/data_dir.py)
register_choice_resolver()  # ${choice:GROUP}: a config group's option on the command line, or null (kpflow/utils/group_choice.py)


def load_policy(path, task=None, input_margin: float | None = 10.0, **overrides):
    """The policy a checkpoint holds, ready to act (``reset(seed)``, ``act(obs) -> action chunk``), built as its config
    says (:mod:`kpflow.policies.config`: its kind, settings, transport and keypoint layout), on the CPU: a path, or
    ``release:NAME`` for a released one (``kpflow.load_policy("release:pusht_standard_fast")`` acts as its results
    page measured it, with no overrides).

    ``overrides``: ``kind`` (``kcfm``: the K-CFM as it is, ``transported_kcfm``: transported online over the source
    index saved beside the checkpoint), ``steps``, ``solver``, ``execute``, ``reach``, ``turn_deg`` and ``transport``
    (a mapping of :class:`~kpflow.policies.config.TransportConfig` options); ``task``: the task it acts in (a task
    object; None: the layout the checkpoint records); ``input_margin``: how far outside its training keypoints an
    observation may lie (:mod:`kpflow.policies.checks`). One builder makes it, the one ``kpflow-evaluate`` and
    ``kpflow-serve`` use (:class:`kpflow.policies.factory.PolicyBuilder`).

    A checkpoint trained on a GPU loads too; a missing file raises ``FileNotFoundError``, a corrupt one or an option
    it ignores a ``ValueError`` naming it.
    """
    from kpflow.policies.factory import build

    return build(path, overrides, task, None, input_margin)
