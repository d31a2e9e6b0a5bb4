"""Whether a round's winner owns its gain: the cost at its optimum with its own parameters at
their neutral values. When the model it extends does as well there, the gain belongs to the
current model's parameters (a baseline stuck on a bound or short of its optimum), which is
refitted from that point instead (`refitted_if_not_own`).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp

from .continuous import reconverge
from .held_out import HeldOutSet
from .joint_model import Superset, _cost
from .state import CandidateFits, CurrentModel, SearchOptions, SearchState

#: `diagnose_logs`' rounds refit the current model at most this many times per round
#: (each refit lowers its cost by more than the BIC threshold, so the bound only caps the time)
MAX_REFITS = 3


def checked_label(scores, fits: CandidateFits | None, bic_threshold: float) -> str | None:
    """The continuous candidate whose gain the round would credit: the accepted one fitted in
    `fits` with the lowest dBIC, else the fitted one with the lowest dBIC when it passes the
    BIC test (it leads the pair search); None when there is none."""
    if fits is None:
        return None
    fitted = [s for s in scores if s.label in fits.labels and not s.not_fitted and not s.members]
    accepted = [s for s in fitted if s.accepted]
    lead = min(accepted or fitted, key=lambda s: s.delta_bic, default=None)
    if lead is None or not (lead.accepted or lead.delta_bic < -bic_threshold):
        return None
    return lead.label


def neutral_cost(superset: Superset, state: SearchState, fits: CandidateFits, label: str) -> float:
    """The fit logs' weighted cost at `label`'s optimum with its own parameters at their
    neutral values: the current model's slot layout at that optimum's baseline parameters,
    accepted extensions and per-log unknowns (one model evaluation, nothing refitted)."""
    cur = state.current
    v = fits.variables(label)
    r = _cost(superset.joint, v, jnp.asarray(cur.idx), jnp.asarray(cur.logf), superset.sigma_j, state.step)
    cost = float(jnp.sum(r**2))
    return cost if math.isfinite(cost) else float("inf")


def refitted_if_not_own(
    superset: Superset, held: HeldOutSet, options: SearchOptions, state: SearchState, scores, fits
) -> CurrentModel | None:
    """The current model refitted, when the gain of the round's candidate (`checked_label`) is
    not its own: its `neutral_cost` passes the BIC test against the current model
    (`N ln(C_neutral / C) < -bic_threshold`, no parameter added), so the current model's own
    parameters reach a better optimum without it. The refit starts from that point
    (`continuous.reconverge`); the finding goes to `state.notes`. None when the gain is the
    candidate's own."""
    label = checked_label(scores, fits, options.bic_threshold)
    if label is None:
        return None
    cur, N = state.current, superset.N
    cost_n = neutral_cost(superset, state, fits, label)
    dbic = N * math.log(max(cost_n, 1e-300) / cur.cost)
    if not dbic < -options.bic_threshold:
        return None
    v = fits.variables(label)
    theta = superset.theta_of(v, cur.idx, cur.logf)
    at_point = dataclasses.replace(cur, v=v, cost=cost_n, ho=held.residuals(theta[None], state.step)[0])
    refit = reconverge(superset, held, options, dataclasses.replace(state, current=at_point), fits.size)
    what = "baseline" if not state.accepted else "model with the accepted cause(s)"
    text = (
        f"{label}'s gain is not its own: at its optimum with its parameters neutral, the {what} costs "
        f"{cost_n:.6g} against {cur.cost:.6g} (dBIC {dbic:.1f} without a new parameter), so the {what} was stuck "
        f"short of its optimum (its parameters on a bound or its fit unfinished); it was refitted from that point "
        f"(cost {refit.cost:.6g}) and round {state.round + 1} was scored again against it"
    )
    options.say(f"  round {state.round + 1}: {text}")
    state.notes.append({"round": state.round + 1, "text": text})
    return refit
