"""A copy of an env that records to a ``.rrd`` file never overwrites that file.

``render_mode="human"`` renders at every step, so a ``copy.deepcopy`` for a look-ahead
(or an env pickled as a checkpoint and resumed) rendered to the same ``rerun_path`` and
reopened it, truncating the original's recording: 8 steps recorded, a copy made after
the 4th stepped once, and the file held 2 steps. The copy now writes the first free
sibling (``env-2.rrd``, ...), named by ``env.unwrapped.rerun_file``.
"""

from __future__ import annotations

import copy
import pickle
import re
import subprocess
import sys

import gymnasium

import envs  # noqa: F401  (registers the envs)
from tests.envs.gym.test_actions import short


def rows(path) -> int:
    """Rows (logged time points of the track) in a ``.rrd`` file, by rerun's own reader."""
    out = subprocess.run([sys.executable, "-m", "rerun", "rrd", "stats", str(path)],
                         capture_output=True, text=True, check=True).stdout
    return int(re.search(r"^num_rows = (\d+)", out, re.M).group(1))


def test_a_copy_of_a_recording_env_does_not_overwrite_its_rrd(tmp_path):
    rrd = tmp_path / "env.rrd"
    env = gymnasium.make("osa/Search-v1", scenario=short(), render_mode="human",
                         rerun_path=str(rrd)).unwrapped
    env.reset(seed=0)
    for k in range(4):
        env.step(k % 3)
    look = copy.deepcopy(env)  # a look-ahead
    look.step(9)
    resumed = pickle.loads(pickle.dumps(env))  # a checkpoint, resumed
    resumed.step(9)
    for k in range(4):
        env.step(k % 3)
    for e in (env, look, resumed):
        e.close()
    assert env.rerun_file == str(rrd)
    assert look.rerun_file == str(tmp_path / "env-2.rrd")
    assert resumed.rerun_file == str(tmp_path / "env-3.rrd")
    assert rows(rrd) == 8  # every step of the original
    assert rows(look.rerun_file) == 1 and rows(resumed.rerun_file) == 1
