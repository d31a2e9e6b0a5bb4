"""A round's winner must own its gain (`identify._diagnose.own_gain`).

The failure it guards against (issue 61, the flexible servo rig): a baseline stuck short of its
optimum hands its own gain to the first candidate fitted from it, which is then named at a
neutral value (an actuator lag of 1.6e-35 s there). Reproduced on the pendulum of
`test_diagnose.py` (4 s logs here, to save time) with no hidden effect, its baseline fit stopped
after two Levenberg-Marquardt steps (cost 8410 where the data's noise gives ~800): without the
guard `sensor_gain_offset:theta1` is named at a gain of ~1 (measured 2026-12-07; on the 8 s logs
1.0001, dBIC -5655, held-out gain 5.9x). About 100 s of CPU, most of it compiling.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from diagnose_cases import PENDULUM_NOISE, PENDULUM_PARAMS, pendulum, pendulum_logs  # tests/ is on sys.path

import flexdyn as fd
from identify._diagnose.own_gain import checked_label
from identify._diagnose.search import diagnose_logs
from identify._diagnose.split import split_logs

# the baseline fit left unfinished on purpose: one stage, one start, two steps, no restart
STOPPED_SHORT = {"max_steps": 2, "n_stages": 1, "n_starts": 1, "max_restarts": 0}


@pytest.mark.slow  # (87 s in CI's run of 2026-12-07, the slowest of the suite)
def test_a_baseline_stuck_short_of_its_optimum_gives_no_cause_its_gain():
    logs = pendulum_logs(pendulum(), 14, t=np.arange(401) / 100.0)  # no hidden effect
    fit_logs, held, desc = split_logs(logs[:2], logs[2:])
    diag = diagnose_logs(
        fd.rigs.rigid_pendulum(),
        PENDULUM_PARAMS,
        fit_logs,
        held,
        {"theta1": PENDULUM_NOISE},
        split=desc,
        catalogue=("sensor_gain_offset", "sensor_delay"),
        max_effects=1,
        fit_options=STOPPED_SHORT,
    )
    assert diag.named == [], diag.summary()
    guard = [n for n in diag.notes if "gain is not its own" in n["text"]]
    assert len(guard) == 1 and guard[0]["round"] == 1, diag.notes
    # the causes' baseline is the refitted one: at the noise (cost ~ N), far below the stopped fit
    n = diag.costs["n_fit"]
    assert diag.baseline.cost > 5 * n, diag.baseline.cost  # (8410 for 802 residuals)
    assert diag.costs["fit"]["baseline"] < 1.2 * n, diag.costs
    ratio = diag.held_out["baseline"]["theta1"] / diag.held_out["noise_floor"]["theta1"]
    assert 0.8 < ratio < 1.2, ratio


class _S:
    def __init__(self, label, dbic, accepted, not_fitted="", members=()):
        self.label, self.delta_bic, self.accepted = label, dbic, accepted
        self.not_fitted, self.members = not_fitted, members


class _Fits:
    labels = ["a", "b", "c"]


def test_the_candidate_checked_is_the_one_the_round_would_credit():
    """The accepted one with the lowest dBIC (whatever the scores' order); else the leader by
    dBIC when it passes the BIC test (it would lead the pair search); else none."""
    nan = math.nan
    scores = [_S("a", -50.0, True), _S("b", -80.0, True), _S("c", -200.0, False), _S("d", -900.0, True)]
    assert checked_label(scores, _Fits(), 10.0) == "b"  # ("d": not fitted in `fits`, e.g. a pair's label)
    assert checked_label([_S("a", -50.0, False), _S("b", -80.0, False)], _Fits(), 10.0) == "b"
    assert checked_label([_S("a", -5.0, False), _S("b", nan, False, "never left its start")], _Fits(), 10.0) is None
    assert checked_label(scores, None, 10.0) is None
