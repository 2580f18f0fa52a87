"""Numba's set-up is left out of later garbage collections while a command runs
(``training.inference._freeze_numba_setup``).

The first kernel ``FastAdvance`` loads sets numba up (~90 000 long-lived objects); where that happens
inside a command (``warp_hcell.core.cli.run_main``), the objects alive are frozen (``gc.freeze``), so
that later full collections do not walk them again, and objects made afterwards are collected as usual.
A library call (a notebook, a script) leaves the collector alone. Each case runs in a fresh process: the
freeze is once per process. The step asks for the tangent, whose kernels are numba's (the planar step alone
may be precompiled, ``training.precompiled``, and set nothing up).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import gc, json, sys, weakref
import numpy as np
from homogenization.backends import make_cell_model
from warp_hcell.core.cli import run_main
from warp_hcell.mesostructures.hcell import h_cell

def step(argv):
    cell = make_cell_model("ann", threads=1)
    state = cell.init_state(h_cell(55.0), 3)
    cell.step(state, np.tile([2e-5, 1e-5], (3, 1)), with_tangent=True)
    return 0

if sys.argv[1] == "command":
    assert run_main(step, []) == 0
else:
    step(None)

class Node:
    pass

node = Node()
node.self = node
ref = weakref.ref(node)
del node
gc.collect()
print(json.dumps({"frozen": gc.get_freeze_count(), "cycle_collected": ref() is None}))
"""


def _run(mode: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", SCRIPT, mode], env=env, cwd=ROOT, capture_output=True,
                          text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("mode", ["command", "library"])
def test_numba_set_up_is_frozen_only_inside_a_command_and_later_cycles_are_collected(mode):
    result = _run(mode)
    if mode == "command":
        assert result["frozen"] > 10_000
    else:
        assert result["frozen"] == 0
    assert result["cycle_collected"]
