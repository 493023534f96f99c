"""The client side imports no training stack: ``import kpflow.serving.client`` and ``kpflow-connect`` (issue 66) load
numpy, websockets and msgpack, never torch or Lightning; ``kpflow.serving``'s names load on first use and
``kpflow.load_policy`` stays where it was."""

import subprocess
import sys

HEAVY = ("torch", "lightning")


def modules_after(code: str) -> set[str]:
    """The top-level modules a fresh interpreter holds after running ``code``."""
    probe = f"{code}\nimport sys\nprint(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return set(out.split())


def test_the_client_and_kpflow_connect_import_neither_torch_nor_lightning():
    loaded = modules_after("import kpflow.serving.client\nimport kpflow.examples.connect")
    assert {"numpy", "websockets", "msgpack"} <= loaded
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_kpflow_connect_help_imports_neither_torch_nor_lightning():
    loaded = modules_after(
        "import contextlib, io\nfrom kpflow.examples.connect import main\n"
        "with contextlib.suppress(SystemExit), contextlib.redirect_stdout(io.StringIO()):\n    main(['--help'])"
    )
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_kpflow_serving_names_load_on_first_use():
    import kpflow.serving as serving

    assert serving.__all__ == [
        "BatchedNetwork",
        "Deployment",
        "PolicyClient",
        "PolicyMetadata",
        "PolicyServer",
        "PolicyServerError",
        "load_deployment",
    ]
    assert sorted(serving._LAZY) == serving.__all__
    for name in serving.__all__:
        assert getattr(serving, name).__name__ == name
        assert name in dir(serving)
    from kpflow.serving import PolicyClient, PolicyServer
    from kpflow.serving.client import PolicyClient as client_class
    from kpflow.serving.server import PolicyServer as server_class

    assert PolicyClient is client_class and PolicyServer is server_class
    try:
        serving.no_such_name
    except AttributeError as error:
        assert "no_such_name" in str(error)
    else:
        raise AssertionError("an unknown name must raise AttributeError")


def test_load_policy_is_reachable_from_import_kpflow():
    import kpflow

    assert callable(kpflow.load_policy)
    assert kpflow.load_policy.__module__ == "kpflow"
