"""No hidden process state: importing torchvol changes no environment variable, allocator or
thread setting and imports no compiler stack; the tuning that helps is one call, `tune_process`."""

import json
import os
import platform
import subprocess
import sys
import textwrap

import torchvol as tv
from torchvol.runtime import heap, process

# what the children start from: no wait policy or malloc tuning inherited from this process or
# the user's shell (an earlier test of the CLI tunes this process itself)
UNTUNED = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", heap.OPT_OUT, heap.TUNABLES,
                                                            *heap.ENVIRONMENT)}


def child(code: str, env: dict[str, str] | None = None) -> dict:
    """`code` run in a fresh interpreter; -> the JSON object it prints last."""
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env={**UNTUNED, **(env or {})}, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_torchvol_changes_nothing_imports_no_torch_and_takes_under_a_second():
    seen = child("""
        import json, os, sys, time
        before = dict(os.environ)
        start = time.perf_counter()
        import torchvol
        seconds = time.perf_counter() - start
        print(json.dumps(dict(seconds=seconds, same_environ=dict(os.environ) == before,
                              torch="torch" in sys.modules, dynamo="torch._dynamo" in sys.modules)))
    """)
    assert seen["same_environ"] and not seen["torch"] and not seen["dynamo"], seen
    assert seen["seconds"] < 1.0, f"import torchvol took {seen['seconds']:.2f} s"


def test_the_public_api_imports_no_dynamo_and_leaves_the_environment_alone():
    seen = child("""
        import json, os, sys
        before = dict(os.environ)
        import torchvol as tv
        names = [getattr(tv, name) for name in tv.__all__]
        tv.render, tv.SceneDataset, tv.preset
        print(json.dumps(dict(same_environ=dict(os.environ) == before, dynamo="torch._dynamo" in sys.modules,
                              names=len(names))))
    """)
    assert seen == {"same_environ": True, "dynamo": False, "names": len(tv.__all__)}


def test_an_eager_render_imports_no_dynamo():
    seen = child("""
        import json, sys
        import torchvol as tv
        tv.render(tv.preset("cloud-puff", width=4, height=4), compile="off")
        print(json.dumps(dict(dynamo="torch._dynamo" in sys.modules)))
    """)
    assert seen == {"dynamo": False}


def test_the_package_lists_its_public_names_and_refuses_others():
    assert {"render", "preset", "Recipe", "SceneDataset", "tune_process"} <= set(tv.__all__) <= set(dir(tv))
    assert tv.render.__module__ == "torchvol.renderer.executor"
    assert isinstance(tv.__version__, str)
    try:
        tv.no_such_name
    except AttributeError as error:
        assert "no_such_name" in str(error)
    else:
        raise AssertionError("tv.no_such_name did not raise AttributeError")


def test_tune_process_sets_the_wait_policy_before_torch_and_the_heap():
    code = """
        import dataclasses, json, os
        import torchvol as tv
        tuned = tv.tune_process()
        import torch
        print(json.dumps(dict(policy=os.environ.get("OMP_WAIT_POLICY"), tuned=dataclasses.asdict(tuned),
                              again=dataclasses.asdict(tv.tune_process()))))
    """
    seen = child(code)
    assert seen["policy"] == process.WAIT_POLICY == "PASSIVE"
    assert seen["tuned"]["wait_policy"] == "PASSIVE" and seen["tuned"]["wait_policy_applies"] is True
    assert seen["tuned"]["heap"] is (sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc")
    # called again after torch loaded: the policy holds, but too late to change OpenMP's
    assert seen["again"]["wait_policy"] == "PASSIVE" and seen["again"]["wait_policy_applies"] is False
    # the user's own settings win
    assert child(code, {"OMP_WAIT_POLICY": "ACTIVE"})["policy"] == "ACTIVE"
    assert child(code, {heap.OPT_OUT: "system"})["tuned"]["heap"] is False


def test_imports_uncollected_freezes_what_it_imported_and_restores_the_collector():
    """The command's imports run without Python's cyclic collector and leave their objects frozen
    (never scanned again, shared with forked workers); the collector is on again after, or stays
    off where it was off; an import that fails still restores it."""
    seen = child("""
        import gc, json
        from torchvol.runtime.process import imports_uncollected
        with imports_uncollected():
            inside = gc.isenabled()
            import fractions
        frozen, after = gc.get_freeze_count(), gc.isenabled()
        gc.disable()
        try:
            with imports_uncollected():
                import no_such_module_here
        except ImportError:
            pass
        print(json.dumps(dict(inside=inside, frozen=frozen, after=after, off_stays_off=not gc.isenabled())))
    """)
    assert seen == {"inside": False, "frozen": seen["frozen"], "after": True, "off_stays_off": True}, seen
    assert seen["frozen"] > 1000, seen
