from __future__ import annotations

import os
import subprocess
import sys

import pytest


def run_fresh(code: str, **env: str) -> str:
    """Run ``code`` in a fresh interpreter without THP_MEM_ALLOC_ENABLE and GOMP_SPINCOUNT (plus ``env``); its
    stdout."""
    environ = {k: v for k, v in os.environ.items() if k not in ("THP_MEM_ALLOC_ENABLE", "GOMP_SPINCOUNT")} | env
    done = subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_importing_the_package_loads_nothing_and_sets_nothing():
    out = run_fresh("import os, sys, evlatcorr, evlatcorr.lightning\n"
                    "print(os.environ.get('THP_MEM_ALLOC_ENABLE'), 'torch' in sys.modules)\n"
                    "print(evlatcorr.EventLatencyCorrector.__module__, evlatcorr.lightning.MODELS is not None)")
    assert out.splitlines() == ["None False", "evlatcorr.correction True"]


def test_an_unknown_attribute_is_an_attribute_error():
    import evlatcorr

    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        evlatcorr.nope  # noqa: B018
    assert {"EventLatencyCorrector", "prefer_large_pages", "__version__"} <= set(dir(evlatcorr))


def test_submodules_are_found_by_attribute_as_before():
    # `import evlatcorr` used to import these; code that reads them by attribute keeps working
    out = run_fresh("import sys, evlatcorr\n"
                    "print('evlatcorr.search' in sys.modules, evlatcorr.search.search_constant_latency.__name__,\n"
                    "      evlatcorr.lightning.cli.__name__, hasattr(evlatcorr, 'not_a_module'))")
    assert out == "False search_constant_latency evlatcorr.lightning.cli False"


@pytest.mark.parametrize(("given", "expected"), [(None, "1 True"), ("0", "0 False"), ("1", "1 True")])
def test_prefer_large_pages_keeps_what_the_environment_says(given, expected):
    env = {} if given is None else {"THP_MEM_ALLOC_ENABLE": given}
    code = "import os, evlatcorr; ok = evlatcorr.prefer_large_pages(); print(os.environ['THP_MEM_ALLOC_ENABLE'], ok)"
    assert run_fresh(code, **env) == expected


@pytest.mark.parametrize(("given", "expected"), [(None, "3000 True"), ("300000", "300000 False")])
def test_prefer_short_spin_keeps_what_the_environment_says(given, expected):
    env = {} if given is None else {"GOMP_SPINCOUNT": given}
    code = "import os, evlatcorr; ok = evlatcorr.prefer_short_spin(); print(os.environ['GOMP_SPINCOUNT'], ok)"
    assert run_fresh(code, **env) == expected


def test_the_command_asks_for_large_pages_before_its_first_import_of_torch():
    # the console script and `python -m evlatcorr` run evlatcorr.__main__.main
    code = ("import os, sys, builtins\n"
            "real_import = builtins.__import__\n"
            "seen = []\n"
            "def spy(name, *args, **kwargs):\n"
            "    if name == 'torch' and not seen:\n"
            "        seen.append((os.environ.get('THP_MEM_ALLOC_ENABLE'), os.environ.get('GOMP_SPINCOUNT')))\n"
            "    return real_import(name, *args, **kwargs)\n"
            "builtins.__import__ = spy\n"
            "from evlatcorr.__main__ import main\n"
            "assert 'torch' not in sys.modules\n"
            "try:\n"
            "    main(['--help'])\n"
            "except SystemExit:\n"
            "    pass\n"
            "print(seen)")
    assert run_fresh(code).splitlines()[-1] == "[('1', '3000')]"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm; glibc's mallopt")
@pytest.mark.parametrize(("opt_out", "expected"), [(None, "True True"), ("0", "False False")])
def test_keep_freed_memory_keeps_a_freed_tensor_resident_unless_opted_out(opt_out, expected):
    # 64 MB touched and freed: kept resident for the next tensor, or handed back to the system (the default)
    env = {} if opt_out is None else {"EVLATCORR_KEEP_FREED_MEMORY": opt_out}
    code = ("import os, torch, evlatcorr\n"
            "kept = evlatcorr.keep_freed_memory()\n"
            "def resident(): return int(open('/proc/self/statm').read().split()[1]) * os.sysconf('SC_PAGE_SIZE')\n"
            "before = resident(); x = torch.ones(2**24); del x\n"
            "print(kept, resident() - before > 2**25)")
    assert run_fresh(code, **env) == expected
