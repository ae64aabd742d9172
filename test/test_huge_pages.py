"""numpy's huge-page advice: off for the programs' processes unless the user chose it."""
import os
import subprocess
import sys

import pytest

from meshfg_ros import huge_pages

pytestmark = pytest.mark.skipif(huge_pages._toggle() is None, reason="this numpy has no huge-page switch")

PROGRAM = ("import numpy\n"
           "from meshfg_ros import huge_pages\n"
           "configured = huge_pages.configure()\n"
           "current = numpy._core.multiarray._set_madvise_hugepage(False)\n"
           "print(configured, current)\n")


def _run(setting: str | None) -> str:
    env = {key: value for key, value in os.environ.items() if key != huge_pages.ENVIRONMENT_VARIABLE}
    if setting is not None:
        env[huge_pages.ENVIRONMENT_VARIABLE] = setting
    return subprocess.run([sys.executable, "-c", PROGRAM], env=env, capture_output=True, text=True,
                          check=True).stdout.split()


def test_configure_turns_the_advice_off_where_the_user_did_not_choose():
    assert _run(None) == ["False", "False"]


@pytest.mark.parametrize("setting, advised", [("1", "True"), ("0", "False")])
def test_a_users_numpy_madvise_hugepage_stays_in_force(setting, advised):
    assert _run(setting) == [advised, advised]

