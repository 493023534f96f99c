"""Released files by name (kpflow/utils/releases.py): ``release:NAME`` is looked for in $KPFLOW_RELEASE_DIR, then the
package's kpflow/release/ (shipped in the wheel; a clone's release/ links to it), then the user cache; found nowhere,
the error names every folder looked in and what this version ships. Every checkpoint reader takes the name
(``kpflow.load_policy``, ``read_checkpoint``), and ``${release:NAME}`` resolves in configs. No network."""

import glob
import os
import tomllib
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import kpflow
from kpflow.utils import releases
from kpflow.utils.checkpoint import read_checkpoint
from kpflow.utils.releases import ENV, release_path, resolve_release, search_dirs

ROOT = Path(__file__).resolve().parents[1]
SMALL = "pusht_table1_kcfm_35_corrected"  # the smallest released checkpoint (2.9 MB)


@pytest.fixture
def places(tmp_path, monkeypatch):
    """Three empty folders in the lookup's places: $KPFLOW_RELEASE_DIR, the package's release/, the user cache."""
    env, clone, cache = (tmp_path / name for name in ("env", "clone", "cache"))
    for folder in (env, clone, cache / "kpflow" / "release"):
        folder.mkdir(parents=True)
    monkeypatch.setenv(ENV, str(env))
    monkeypatch.setattr(releases, "package_dir", lambda: clone)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    return env, clone, cache / "kpflow" / "release"


def test_the_first_place_holding_the_file_wins(places):
    env, clone, cache = places
    for folder in (cache, clone, env):
        (folder / "mine.ckpt").write_bytes(b"x")
        assert release_path("mine") == folder / "mine.ckpt"  # each newly written one comes earlier in the order
    (cache / "store.zarr").mkdir()
    assert release_path("store.zarr") == cache / "store.zarr"  # a name with a suffix is the file's whole name
    assert resolve_release("release:mine") == env / "mine.ckpt" and resolve_release("runs/x.ckpt") == Path(
        "runs/x.ckpt"
    )


def test_a_name_found_nowhere_says_where_it_looked_and_how_to_get_it(places, monkeypatch):
    env, clone, cache = places
    (clone / "other.ckpt").write_bytes(b"x")
    (clone / "other.source_index.npz").write_bytes(b"x")
    with pytest.raises(FileNotFoundError) as error:
        release_path("mine")
    message = str(error.value)
    assert message.startswith(
        f"no released file mine.ckpt: looked in {env} ($KPFLOW_RELEASE_DIR); {clone} (the package's releases); {cache} (the user cache)"
    )
    assert "released there: other." in message and "source_index" not in message
    assert f"kpflow {kpflow.__version__} ships its releases in the package (kpflow/release/)" in message
    assert f"goes into {cache}/ or a folder named by KPFLOW_RELEASE_DIR" in message and "<owner>" not in message
    monkeypatch.delenv(ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache.parent.parent / "nothing"))
    assert [what for _, what in search_dirs()][:2] == ["$KPFLOW_RELEASE_DIR (not set)", "the package's releases"]
    with pytest.raises(
        FileNotFoundError,
        match=r"looked in \$KPFLOW_RELEASE_DIR \(not set\); .* \(the package's releases\); .*nothing/kpflow/release \(the user cache, missing\); released there: other\. kpflow",
    ):
        release_path("mine")


@pytest.mark.parametrize("name", ["", "..", "../mine", "sub/mine", "/abs/mine.ckpt"])
def test_a_path_is_not_a_name(name):
    with pytest.raises(ValueError, match="is not a released file's name: give its name alone"):
        release_path(name)


def test_the_package_ships_its_releases_and_they_load_by_name(tmp_path, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    package = ROOT / "kpflow" / "release"
    assert releases.package_dir() == package and release_path(SMALL) == package / f"{SMALL}.ckpt"
    assert (ROOT / "release").resolve() == package  # a clone's release/ is the package's folder
    policy = kpflow.load_policy(f"release:{SMALL}")
    assert policy.policy.model.hparams.n_keypoints == 25  # shown its goal within reach, as its record says
    assert (
        read_checkpoint(f"release:{SMALL}")["state_dict"].keys()
        == read_checkpoint(ROOT / "release" / f"{SMALL}.ckpt")["state_dict"].keys()
    )
    with pytest.raises(FileNotFoundError, match=f"no released file {SMALL}x.ckpt: .*released there: .*{SMALL}"):
        kpflow.load_policy(f"release:{SMALL}x")


def test_configs_resolve_release_names(places):
    env, _, _ = places
    (env / "demos.zarr").mkdir()
    assert OmegaConf.create({"data": {"path": "${release:demos.zarr}"}}).data.path == str(env / "demos.zarr")
    with pytest.raises(Exception, match="no released file missing.zarr"):
        OmegaConf.create({"path": "${release:missing.zarr}"}).path


def test_the_wheel_carries_every_released_file():
    """pyproject's package data, globbed as setuptools globs it (recursive, no hidden names for ``*``), covers every
    file under kpflow/release/: a user without a clone loads ``release:NAME`` from the installed package."""
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["kpflow"]
    shipped = {
        os.path.normpath(f)
        for p in patterns
        for f in glob.glob(str(ROOT / "kpflow" / p), recursive=True)
        if os.path.isfile(f)
    }
    released = {
        os.path.normpath(os.path.join(d, f)) for d, _, files in os.walk(ROOT / "kpflow" / "release") for f in files
    }
    assert released and released <= shipped, sorted(released - shipped)[:5]
