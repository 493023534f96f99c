"""``${choice:GROUP}``: the option a config group was given on the command line (``map=gp`` -> ``gp``), or null.

Hydra's own ``${hydra:runtime.choices.GROUP}`` fails where no Hydra app runs (a config composed in a notebook or a
test); this resolver answers null there, as it does for a group left at ``null``. It lets a policy take a group's
choice as an option by name (``policy.transport.map: ${choice:map}``) while null still means "not given".
"""


def group_choice(group: str) -> str | None:
    """The option chosen for ``group`` in the running Hydra app (None: none chosen, or no app)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return None
    return HydraConfig.get().runtime.choices.get(str(group))


def register_resolver() -> None:
    """Register the OmegaConf resolver ``choice`` (``${choice:GROUP}``), once."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("choice"):
        OmegaConf.register_new_resolver("choice", group_choice)
