"""torch_ampn.utils.threads: the OpenMP wait policy is set before torch starts, unless the user chose."""

import os
import subprocess
import sys

from torch_ampn.utils.threads import WAIT_POLICY, configure_threads

SHOW = "import os, sys; {imports}; print(os.environ.get('GOMP_SPINCOUNT'), os.environ.get('OMP_WAIT_POLICY'))"
CONTROLLED = ("AMPN_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT")


def _run(imports, **env):
    clean = {k: v for k, v in os.environ.items() if k not in CONTROLLED}
    command = [sys.executable, "-c", SHOW.format(imports=imports)]
    out = subprocess.run(command, env={**clean, **env}, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_import_sets_the_wait_policy_before_torch():
    assert _run("import torch_ampn") == ["None", WAIT_POLICY]
    assert _run("import torch_ampn.cli.train") == ["None", WAIT_POLICY]  # the torch-ampn command
    assert _run("import torch; import torch_ampn") == ["None", "None"]  # too late: left alone


def test_the_users_choice_and_off_are_left_alone():
    assert _run("import torch_ampn", OMP_WAIT_POLICY="ACTIVE") == ["None", "ACTIVE"]
    assert _run("import torch_ampn", GOMP_SPINCOUNT="5") == ["5", "None"]
    assert _run("import torch_ampn", AMPN_THREADS="off") == ["None", "None"]


def test_configure_threads_reports_what_it_did(monkeypatch):
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    env = {}
    assert configure_threads(env) == f"wait={WAIT_POLICY}" and env == {"OMP_WAIT_POLICY": WAIT_POLICY}
    monkeypatch.setitem(sys.modules, "torch", object())  # torch imported: its pool has read its settings
    env = {}
    assert configure_threads(env) == "late" and env == {}
    assert configure_threads({"AMPN_THREADS": "OFF"}) == "off"
    assert configure_threads({"OMP_WAIT_POLICY": "ACTIVE"}) == "user"
