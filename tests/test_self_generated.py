"""Self-generated demonstrations: a policy's own Push-T episodes collected into a store (``kpflow-collect
policy=...``), and stores combined into one dataset with their provenance (:func:`combine_stores`)."""

from __future__ import annotations

import numpy as np
import pytest
from hydra.utils import instantiate

from kpflow.data.episode_store import EpisodeStore
from kpflow.data.store_merge import combine_stores
from kpflow.tasks.pusht.collection import collect_pusht
from kpflow.tasks.pusht.geometry import observation_keypoints
from kpflow.tasks.pusht.scene import standard_config
from tests.helpers import compose_config


def test_a_policy_collects_its_own_episodes_on_the_standard_start_states(walk_store, tmp_path):
    """``kpflow-collect policy=transport ... condition=standard first_index=7`` composes; its policy's episodes start
    at Diffusion Policy's start states for seeds 7, 8, ..., are recorded with their config index and the policy as
    their source, and the store is continued only by the same collection."""
    cfg = compose_config(
        "collect",
        ["policy=transport", "data=pusht_store", f"data.path={walk_store}", "condition=standard", "first_index=7"],
        tmp_path,
    )
    policy = instantiate(cfg.policy)
    path = tmp_path / "own.zarr"
    kwargs = dict(split="standard", goal="fixed", max_steps=12, keep_failures=True, progress=False, policy=policy, source="policy:transport",
                  first_index=cfg.first_index)  # fmt: skip
    summary = collect_pusht(path, 2, **kwargs)
    assert summary["episodes"] == 2 and summary["attempts"] == 2
    store = EpisodeStore(path)
    assert store.attrs["source"] == "policy:transport" and store.attrs["split"] == "standard"
    assert [store.episode_attrs(i)["config_index"] for i in range(2)] == [7, 8]
    first = store.episode(0)
    c = standard_config(7)
    np.testing.assert_allclose(
        first["keypoints"][0], observation_keypoints(c.block_pose, c.goal_pose, c.agent_pos), atol=1e-3
    )
    assert len(first["action"]) == 12 and not store.episode_attrs(0)["success"]
    again = collect_pusht(path, 2, **kwargs)  # the same collection, complete: nothing more to do
    assert again["resumed_from"] == 2 and again["attempts"] == 0
    with pytest.raises(ValueError, match="another collection"):
        collect_pusht(path, 2, **{**kwargs, "source": "policy:nearest"})  # a store is continued by its own source only
    with pytest.raises(ValueError, match="source names who acts"):
        collect_pusht(tmp_path / "x.zarr", 1, **{**kwargs, "source": "expert"})
    with pytest.raises(ValueError, match="unknown Push-T split 'standard' for the expert"):
        collect_pusht(tmp_path / "y.zarr", 1, split="standard", progress=False)


def _store(path, fields: dict[str, tuple], n: int, attrs: dict) -> EpisodeStore:
    with EpisodeStore(path, mode="a") as store:
        store.attrs.put(attrs)
        for e in range(n):
            store.add_episode(
                {k: np.full((3 + e, *shape), e, dtype) for k, (dtype, shape) in fields.items()}, attrs={"index": e}
            )
    return EpisodeStore(path)


def test_stores_combine_their_first_episodes_and_shared_fields_with_provenance(tmp_path):
    human = _store(
        tmp_path / "human.zarr",
        {"keypoints": ("float32", (2, 2)), "action": ("float32", (2,)), "state": ("float32", (5,))},
        4,
        {"source": "human"},
    )
    own = _store(
        tmp_path / "own.zarr",
        {"keypoints": ("float32", (2, 2)), "action": ("float32", (2,))},
        2,
        {"source": "policy:transport"},
    )
    out = combine_stores(tmp_path / "both.zarr", [(human.path, 3), (own.path, None)])
    both = EpisodeStore(out)
    assert both.n_episodes == 5 and sorted(both.episode(0)) == ["action", "keypoints"]
    assert [(both.episode_attrs(i)["source"], both.episode_attrs(i)["source_episode"]) for i in range(5)] == [
        (0, 0),
        (0, 1),
        (0, 2),
        (1, 0),
        (1, 1),
    ]
    np.testing.assert_array_equal(both.episode(4)["action"], own.episode(1)["action"])
    provenance = both.attrs["combined_from"]
    assert [(p["episodes"], p["attrs"]["source"]) for p in provenance] == [(3, "human"), (2, "policy:transport")]
    with pytest.raises(FileExistsError):
        combine_stores(out, [(own.path, None)])
    with pytest.raises(ValueError, match="holds 2 episodes; 5 asked for"):
        combine_stores(tmp_path / "x.zarr", [(own.path, 5)])
    with pytest.raises(ValueError, match="'state' is missing"):
        combine_stores(tmp_path / "y.zarr", [(human.path, None), (own.path, None)], fields=["state"])
    odd = _store(tmp_path / "odd.zarr", {"keypoints": ("float64", (2, 2))}, 1, {})
    with pytest.raises(ValueError, match="'keypoints' is stored differently"):
        combine_stores(tmp_path / "z.zarr", [(human.path, None), (odd.path, None)])
    assert not (tmp_path / "x.zarr").exists() and not (tmp_path / "z.zarr").exists()
