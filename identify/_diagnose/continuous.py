"""The continuous candidates of a round: screened, fitted in one vmapped call on the joint model
(`joint_model.Superset`) and scored against the current model; the pair search; the accepted
model refitted alone.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

import flexdyn as fd

from .._model.parameters import x_from_z
from . import catalogue as cat
from .held_out import HeldOutSet
from .joint_model import (
    MAX_REFINEMENTS,
    REFERENCE_DIVISOR,
    SLOTS,
    JointVariables,
    Superset,
    _best_starts,
    _bounds,
    _few_size,
    _finer_step,
    _fit_batch,
    _pad,
    _pad_used,
    _refine,
    _screen,
    _unsaturated,
)
from .notes import _stuck_above_nested
from .scores import Score, _rms_per_channel, gain_standard_error
from .state import CandidateFits, CurrentModel, SearchOptions, SearchState


def score_continuous(
    superset: Superset, held: HeldOutSet, options: SearchOptions, state: SearchState, remaining, v_start: dict
) -> tuple[list[Score], CandidateFits | None]:
    """Fit the continuous candidates `remaining` (multi-start, screened when there are more
    than `options.n_fit`) from the joint model's variables `v_start`, each extending the
    current model `state.current`, and score them against it. Returns the scores and the fits
    (to extend from; None when none was fitted). May make `state.step` finer (`STEP_RECHECK`)."""
    fd.ensure_mapping_headroom()  # each candidate batch compiles programs of its own
    batch, owners = _starts(superset, state.current.layout, remaining)
    if not batch:
        return [], None
    idx = jnp.asarray(np.stack([b[0] for b in batch]))
    logf = jnp.asarray(np.stack([b[1] for b in batch]))
    xe = np.stack([b[2] for b in batch])
    remaining = [c for c in remaining if c in owners]
    screened_out, predicted, why_out = [], {}, {}
    if options.n_fit is not None and len(remaining) > options.n_fit:
        sel, keep, predicted, why_out = _screening(superset, options, state, v_start, owners, remaining, idx, logf, xe)
        screened_out = [c for c in remaining if c.label not in keep]
        owners = [owners[b] for b in sel]
        sel_i = np.asarray(sel, dtype=int)
        idx, logf, xe = idx[sel_i], logf[sel_i], xe[sel_i]
        remaining = [c for c in remaining if c.label in keep]
    scores, fits = [], None
    if not owners:
        options.say("  no continuous candidate is predicted to improve the fit significantly")
    else:
        vs, costs, best, size, not_fitted = _fit_starts(
            superset, options, state, v_start, owners, remaining, idx, logf, xe, predicted
        )
        labels = [c.label for c in remaining if c.label in best]
        thetas = jnp.stack(
            [
                superset.theta_of(vs.take(best[lab]), np.asarray(idx[best[lab]]), np.asarray(logf[best[lab]]))
                for lab in labels
            ]
        )
        fits = CandidateFits(vs, best, idx, logf, held.residuals(thetas, state.step), labels, size)
        for i, lab in enumerate(labels):
            c = next(x for x in remaining if x.label == lab)
            if lab in not_fitted:
                scores.append(_not_fitted_score(options, state, c, float(costs[best[lab]]), not_fitted[lab]))
                continue
            scores.append(
                _fitted_score(superset, held, options, state, c, float(costs[best[lab]]), thetas[i], fits.ho[i])
            )
    scores += [_screened_score(superset, state, c, predicted[c.label], why_out[c.label]) for c in screened_out]
    return scores, fits


def _starts(superset: Superset, layout, candidates) -> tuple[list, list]:
    """Every start of every candidate that fits the slots beside the accepted `layout`: its
    slot layout (`Superset.layout`), and the candidate it belongs to."""
    batch, owners = [], []
    for c in candidates:
        for s in c.starts:
            names_vals = list(layout) + [(n, val, lg) for n, val, lg in zip(c.params, s, c.log_scale)]
            if len(names_vals) > SLOTS:
                continue
            batch.append(superset.layout(names_vals))
            owners.append(c)
    return batch, owners


def _screening(
    superset: Superset, options: SearchOptions, state: SearchState, v_start, owners, remaining, idx, logf, xe
):
    """One Gauss-Newton step from every start (exact Jacobians, all the free parameters)
    predicts each candidate's cost; only the `n_fit` most promising of those predicted to
    pass the BIC test, and to reach at least 10 % of the best one's drop, get the full
    multi-start fit (a second, smaller effect is searched for in the next round). Returns the
    starts to fit (each kept candidate's two most promising), the labels kept, each label's
    predicted cost, and why each other one was left out."""
    joint, N, n_fit, cost = superset.joint, superset.N, options.n_fit, state.current.cost
    xb_cur = x_from_z(_bounds(joint), v_start.zb)
    B = len(owners)
    if state.screen_batch is None:
        state.screen_batch = B
    size = max(state.screen_batch, B)
    rs, Js = _screen(
        joint,
        xb_cur,
        _pad(jnp.asarray(xe), size),
        v_start.y0,
        v_start.offset,
        _pad(idx, size),
        _pad(logf, size),
        superset.sigma_j,
        state.step,
    )
    rs, Js = np.asarray(rs)[:B, superset.used], np.asarray(Js)[:B, superset.used, :]
    predicted, per_start = {}, []
    for b, c in enumerate(owners):
        delta, *_ = np.linalg.lstsq(Js[b], -rs[b], rcond=None)
        pred = float(np.sum((rs[b] + Js[b] @ delta) ** 2))
        per_start.append(pred)
        predicted[c.label] = min(predicted.get(c.label, np.inf), pred)
    n_par = {c.label: len(c.params) for c in remaining}
    promising = [
        lab for lab in predicted if N * math.log(max(predicted[lab], 1e-300) / cost) + n_par[lab] * math.log(N) < 0.0
    ]
    why_out = {lab: "predicted not to lower the BIC" for lab in predicted if lab not in promising}
    if promising:
        best_drop = cost - min(predicted[lab] for lab in promising)
        small = [lab for lab in promising if cost - predicted[lab] < 0.1 * best_drop]
        why_out.update(
            {lab: "under 10 % of the best one's predicted drop; screened again once that is accepted" for lab in small}
        )
        promising = [lab for lab in promising if lab not in small]
    keep = sorted(promising, key=predicted.get)[:n_fit]
    why_out.update(
        {lab: f"ranked below the {n_fit} most promising (n_fit={n_fit})" for lab in promising if lab not in keep}
    )
    options.say(
        "  screening (one Gauss-Newton step per start), predicted costs: "
        + ", ".join(f"{lab} {predicted[lab]:.6g}" for lab in sorted(predicted, key=predicted.get))
    )
    sel = []
    for lab in keep:
        mine = sorted((b for b, c in enumerate(owners) if c.label == lab), key=lambda b: per_start[b])
        sel.extend(mine[:2])
    return sel, keep, predicted, why_out


def _fit_starts(
    superset: Superset, options: SearchOptions, state: SearchState, v_start, owners, remaining, idx, logf, xe, predicted
):
    """The starts `owners` (slot layouts `idx`, `logf`, extension values `xe`) fitted from
    `v_start` in one vmapped call; the candidates none of whose starts moved their
    parameters fitted again from wider starts (`_retry_wider`); at a finer step if the best
    one needs it (`_step_check`), the contenders continued (`_refine`). Returns the
    variables and costs of every start, each candidate's best start, `(batch size, seconds
    the call took)`, and the candidates whose fit never left its starts, label -> why
    (`_never_left`)."""
    joint, sigma_j, max_steps, say = superset.joint, superset.sigma_j, options.max_steps, options.say
    B = len(owners)
    v0 = _start_variables(joint, v_start, xe)
    say(f"round {state.round + 1}: fitting {len(remaining)} candidates ({B} starts) in one vmapped call ...")
    # padded to a few fixed sizes, so that every round reuses the compiled programs
    size = _batch_size(B)
    t_call = time.perf_counter()
    vs, costs, steps = _fit_batch(
        joint, _pad(v0, size), _pad(idx, size), _pad(logf, size), sigma_j, state.step, max_steps
    )
    costs = np.asarray(costs, dtype=float)  # waits for the call
    call_s = time.perf_counter() - t_call
    vs, costs, steps, best = _best_starts(vs, costs, steps, owners)
    starts = _Starts(np.asarray(xe, dtype=float).copy(), len(state.current.layout))
    stayed = starts.stayed(superset, vs, costs, owners)
    tried, wider = {lab: starts.values(owners, lab) for lab in stayed}, {}
    if stayed:
        vs, costs, steps, wider = _retry_wider(
            superset, options, state, v_start, stayed, owners, vs, costs, steps, starts
        )
        vs, costs, steps, best = _best_starts(vs, costs, steps, owners)
    finer = _step_check(superset, options, state, vs, costs, best, owners, idx, logf)
    if finer is not None:  # the fits go on from where they are, at the finer step
        state.step = finer
        t_call = time.perf_counter()
        vs, costs, steps = _fit_batch(
            joint, _pad(vs, size), _pad(idx, size), _pad(logf, size), sigma_j, state.step, max_steps
        )
        costs = np.asarray(costs, dtype=float)
        call_s = time.perf_counter() - t_call  # (what a continuation at this step costs)
        vs, costs, steps, best = _best_starts(vs, costs, steps, owners)
    sized = (size, call_s)
    vs, costs = _refine(
        joint,
        vs,
        costs,
        steps,
        best,
        owners,
        idx,
        logf,
        sigma_j,
        state.step,
        max_steps,
        sized,
        state.current.cost,
        superset.N,
        say,
        predicted=predicted,
    )
    still = set(starts.stayed(superset, vs, costs, owners)) & set(stayed)
    by_label = {c.label: c for c in owners}
    return vs, costs, best, sized, {lab: _never_left(by_label[lab], tried[lab], wider[lab]) for lab in still}


def _batch_size(n: int) -> int:
    """The batch size `n` starts are padded to: one of a few fixed sizes (3, 6, 12, 24), so
    that every round reuses the compiled programs; `n` itself above them."""
    return next(b for b in (3, 6, 12, 24) if b >= n) if n <= 24 else n


def _start_variables(joint, v_start: JointVariables, xe) -> JointVariables:
    """The joint model's variables of a batch of starts: `v_start`'s (the baseline part
    pulled off its bounds, `_unsaturated`) with each start's extension values `xe` (rows)."""
    B = len(xe)
    return JointVariables(
        offset=jnp.tile(v_start.offset, (B, 1)),
        xe=jnp.asarray(xe),
        y0=jnp.tile(v_start.y0, (B, 1)),
        zb=jnp.tile(_unsaturated(joint, v_start.zb), (B, 1)),
    )


#: `_Starts.stayed`: a fit whose every parameter changed by less than this, relative to
#: its start (to its scale for a signed one starting at 0), never left its start
MOVED_RTOL = 1e-9


@dataclasses.dataclass
class _Starts:
    """The extension values each start of a candidate batch began from (`xe`: rows, natural
    values, a log-scale slot's the logarithm), the candidate's own slots after the
    `n_layout` accepted ones; rows are replaced where a start is (`_retry_wider`)."""

    xe: np.ndarray
    n_layout: int

    def _slots(self, c) -> slice:
        return slice(self.n_layout, self.n_layout + len(c.params))

    def left(self, superset: Superset, c, fitted, b: int) -> bool:
        """Whether start `b` of candidate `c` moved any of its parameters (`MOVED_RTOL`)
        to the fitted extension values `fitted` (its row)."""
        sl = self._slots(c)
        x0, x = self.xe[b, sl], np.asarray(fitted, dtype=float)[sl]
        noise = dict(zip(superset.problem.channels, superset.sigma))
        size = [1.0 if log else max(abs(v), cat.signed_scale(n, noise)) for n, log, v in zip(c.params, c.log_scale, x0)]
        return bool(np.any(np.abs(x - x0) > MOVED_RTOL * np.asarray(size)))

    def stayed(self, superset: Superset, vs: JointVariables, costs, owners) -> list[str]:
        """The labels of the candidates with a finished start (finite cost) and none that
        moved its parameters (`left`), in batch order."""
        xe, moved = np.asarray(vs.xe), {}
        for b, c in enumerate(owners):
            if np.isfinite(costs[b]):
                moved[c.label] = moved.get(c.label, False) or self.left(superset, c, xe[b], b)
        return [lab for lab, m in moved.items() if not m]

    def values(self, owners, label: str) -> list[tuple[float, ...]]:
        """The starting values (SI) of `label`'s rows, one tuple per row."""
        out = []
        for b, c in enumerate(owners):
            if c.label == label:
                x = self.xe[b, self._slots(c)]
                out.append(tuple(float(np.exp(v)) if log else float(v) for v, log in zip(x, c.log_scale)))
        return out


def _retry_wider(
    superset: Superset, options: SearchOptions, state: SearchState, v_start, stayed, owners, vs, costs, steps, starts
):
    """Fit the candidates `stayed` (labels) again from starts wider than their own
    (`catalogue.wider_starts`), in one more call padded to the round's batch size (the same
    compiled program, where they fit in it). Each one's rows take the new fits, those that
    left their start first, then by cost (a candidate with fewer rows than new starts keeps
    the best); `starts` is updated with them. Returns the variables, costs and step counts,
    and each candidate's wider starts (label -> value tuples, SI)."""
    joint, layout, say = superset.joint, list(state.current.layout), options.say
    noise = dict(zip(superset.problem.channels, superset.sigma))
    by_label = {c.label: c for c in owners}
    rows, row_owner, wider = [], [], {}
    for lab in stayed:
        c = by_label[lab]
        wider[lab] = list(cat.wider_starts(c, {n: cat.signed_scale(n, noise) for n in c.params}))
        for s in wider[lab]:
            rows.append(superset.layout(layout + [(n, val, lg) for n, val, lg in zip(c.params, s, c.log_scale)]))
            row_owner.append(c)
    idx_r = jnp.asarray(np.stack([r[0] for r in rows]))
    logf_r = jnp.asarray(np.stack([r[1] for r in rows]))
    xe_r = np.stack([r[2] for r in rows])
    n = len(rows)
    size = max(_batch_size(len(owners)), _batch_size(n))
    say(
        f"  round {state.round + 1}: {', '.join(stayed)}: the fit never left its starts; fitting again from wider "
        f"starts ({n} in one call) ..."
    )
    v0 = _start_variables(joint, v_start, xe_r)
    out, c2, s2 = _fit_batch(
        joint,
        _pad(v0, size),
        _pad(idx_r, size),
        _pad(logf_r, size),
        superset.sigma_j,
        state.step,
        options.max_steps,
    )
    c2, s2, xe_out = np.asarray(c2, dtype=float)[:n], np.asarray(s2)[:n], np.asarray(out.xe)[:n]
    costs, steps, retry = costs.copy(), steps.copy(), _Starts(xe_r, starts.n_layout)
    for lab in stayed:
        mine = [b for b, c in enumerate(owners) if c.label == lab]
        new = [r for r, c in enumerate(row_owner) if c.label == lab and np.isfinite(c2[r])]
        new.sort(key=lambda r: (not retry.left(superset, row_owner[r], xe_out[r], r), c2[r]))
        for b, r in zip(mine, new):
            vs = jax.tree_util.tree_map(lambda v, o, b=b, r=r: v.at[b].set(o[r]), vs, out)
            costs[b], steps[b], starts.xe[b] = c2[r], s2[r], xe_r[r]
    return vs, costs, steps, wider


def _never_left(c, first: list, last: list) -> str:
    """`Score.not_fitted` of candidate `c`, whose fit never left its start: from its own
    starts `first`, then from the wider ones `last` (value tuples, SI)."""

    def text(values):
        return ", ".join("(" + ", ".join(f"{v:.3g}" for v in s) + ")" if len(s) > 1 else f"{s[0]:.3g}" for s in values)

    names = c.params[0] if len(c.params) == 1 else "(" + ", ".join(c.params) + ")"
    return (
        f"its fit never left its start from {len(first) + len(last)} starts ({names} = {text(first)}, then wider "
        f"{text(last)}): no evidence for or against the effect"
    )


def _step_check(superset: Superset, options: SearchOptions, state: SearchState, vs, costs, best, owners, idx, logf):
    """The finer step to fit the round's candidates at (`STEP_RECHECK`), or None: checked at
    the optimum of the best candidate, when it would pass the BIC test (said, and noted)."""
    N, cost = superset.N, state.current.cost
    k = {c.label: len(c.params) for c in owners}
    dbic = {lab: N * math.log(max(costs[b], 1e-300) / cost) + k[lab] * math.log(N) for lab, b in best.items()}
    if not dbic or not min(dbic.values()) < -options.bic_threshold:
        return None
    top = min(dbic, key=dbic.get)
    b = best[top]
    v = vs.take(b)
    theta = superset.theta_of(v, np.asarray(idx[b]), np.asarray(logf[b]))
    off, finer = _finer_step(superset.problem, theta, v.y0, state.step, superset.sigma_j)
    if finer is None:
        return None
    text = (
        f"the integration step {float(state.step) * 1e3:.3g} ms is {off:.3g} noise levels off at {top}'s fit "
        f"(against {REFERENCE_DIVISOR}x finer): the candidates' fits go on, and the search, at "
        f"{float(finer) * 1e3:.3g} ms"
    )
    options.say(f"  round {state.round + 1}: {text}")
    state.notes.append({"round": state.round + 1, "text": text})
    return jnp.asarray(float(finer), dtype=jnp.float64)


def _fitted_score(
    superset: Superset, held: HeldOutSet, options: SearchOptions, state: SearchState, c, cost_c, theta, r_ho
) -> Score:
    """The scores of candidate `c` fitted to cost `cost_c` at parameters `theta` (held-out
    residual `r_ho`) against the current model: dBIC `N ln(C_c / C) + k ln N`, the F-test's
    p-value, the held-out gain (ratio of RMS) and its standard error. It is accepted when it
    passes both tests with plausible values (`SearchOptions.plausibility`; a pair's, both
    members'). A fit that ended above the model it holds as a limit is noted
    (`_stuck_above_nested`)."""
    current, N, nb, problem = state.current, superset.N, superset.joint.nb, superset.problem
    k = len(c.params)
    dbic = N * math.log(max(cost_c, 1e-300) / current.cost) + k * math.log(N)
    p_total = nb + current.k + k + len(problem.y0_free) + len(problem.offset_free)
    dof = max(N - p_total, 1)
    F = ((current.cost - cost_c) / k) / (cost_c / dof) if cost_c > 0 else np.inf
    p_value = float(stats.f.sf(F, k, dof)) if np.isfinite(F) else 0.0
    rms_cur = float(np.sqrt(np.mean(current.ho**2)))
    rms_c = float(np.sqrt(np.mean(r_ho**2)))
    gain = rms_cur / rms_c if rms_c > 0 else np.inf
    limit = ", ".join(f"{n} = {superset.neutral[superset.ext_names.index(n)]:g}" for n in c.params)
    stuck = _stuck_above_nested(c, cost_c, current.cost, options.bic_threshold, limit=limit)
    if stuck:
        options.say(f"  round {state.round + 1}: {stuck}")
        state.notes.append({"round": state.round + 1, "text": stuck})
    theta = np.asarray(theta)
    values = {n: float(theta[nb + superset.ext_names.index(n)]) for n in c.params}
    passes = bool(dbic < -options.bic_threshold and gain >= options.min_gain)
    implausible = options.plausibility.judge(c, values) if passes else []
    return Score(
        c.name,
        c.where,
        values,
        cost_c,
        float(dbic),
        p_value,
        _rms_per_channel(held.problem, _pad_used(r_ho, held.used), superset.sigma),
        float(gain),
        passes and not implausible,
        k,
        members=tuple(m.label for m in c.members),
        held_out_gain_se=gain_standard_error(np.asarray(current.ho), np.asarray(r_ho)),
        implausible=implausible,
    )


def _not_fitted_score(options: SearchOptions, state: SearchState, c, cost_c: float, reason: str) -> Score:
    """A candidate whose fit never left its start (`_never_left`: `reason`), at the cost its
    best start ended at: no dBIC, p-value or held-out gain (NaN), never accepted; said and
    noted (`Diagnosis.notes`)."""
    text = f"{c.label}: not fitted: {reason}; it has no detection limit"
    options.say(f"  round {state.round + 1}: {text}")
    state.notes.append({"round": state.round + 1, "text": text})
    nan = float("nan")
    return Score(
        c.name,
        c.where,
        {},
        cost_c,
        nan,
        nan,
        {},
        nan,
        False,
        len(c.params),
        members=tuple(m.label for m in c.members),
        not_fitted=reason,
    )


def _screened_score(superset: Superset, state: SearchState, c, predicted: float, reason: str) -> Score:
    """A candidate screened out (`_screening`): its cost and dBIC as predicted, `reason` why."""
    N, cost = superset.N, state.current.cost
    k = len(c.params)
    cost_c = min(predicted, cost)
    dbic = N * math.log(max(cost_c, 1e-300) / cost) + k * math.log(N)
    return Score(
        c.name,
        c.where,
        {},
        cost_c,
        float(dbic),
        float("nan"),
        {},
        float("nan"),
        False,
        k,
        screened=True,
        screen_reason=reason,
        members=tuple(m.label for m in c.members),
    )


def pair_search(
    superset: Superset,
    held: HeldOutSet,
    options: SearchOptions,
    state: SearchState,
    cands,
    remaining,
    scores,
    fits: CandidateFits | None,
) -> tuple[list, list[Score], CandidateFits | None]:
    """When no single entry of the round (`scores`) is accepted but the best continuous one
    fits far better (dBIC < -bic_threshold), the cause may be two effects that only work
    together: the leader, from its own fit, is paired with every other `remaining` entry
    (`catalogue.pair`), and the pairs are screened, fitted and scored as single entries, with
    k = both entries' parameters. Returns the pairs, their scores and their fits."""
    leaders = [
        s
        for s in scores
        if not s.accepted
        and not s.screened
        and not s.not_fitted
        and not s.members
        and s.delta_bic < -options.bic_threshold
        and any(c.label == s.label and not c.structural for c in cands)
    ]
    if not leaders or any(s.accepted for s in scores):
        return [], [], None
    lead_s = min(leaders, key=lambda s: s.delta_bic)
    lead = next(c for c in cands if c.label == lead_s.label)
    lead_start = tuple(lead_s.params[n] for n in lead.params)
    n_layout = len(state.current.layout)
    pairs = [
        cat.pair(lead, lead_start, c)
        for c in remaining
        if c.label != lead.label and n_layout + len(lead.params) + len(c.params) <= SLOTS
    ]
    if not pairs:
        return pairs, [], None
    options.say(
        f"  no single entry accepted; pairing {lead.label} (dBIC {lead_s.delta_bic:.1f}) with {len(pairs)} others ..."
    )
    v_lead = fits.variables(lead.label)
    pair_scores, pair_fits = score_continuous(superset, held, options, state, pairs, v_lead)
    return pairs, pair_scores, pair_fits


def reconverge(
    superset: Superset, held: HeldOutSet, options: SearchOptions, state: SearchState, sized: tuple
) -> CurrentModel:
    """The accepted model `state.current` refitted alone (no new parameter), from its baseline
    parameters pulled off their bounds (`_unsaturated`, as every candidate of the next round
    starts), until its cost stops falling (`sized`: the round's batch size and call seconds,
    `_few_size`). Without it, a candidate of the next round would get the credit for whatever
    this refit gains."""
    cur, joint, N, max_steps = state.current, superset.joint, superset.N, options.max_steps
    v = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[None], cur.v)
    v = dataclasses.replace(v, zb=_unsaturated(joint, v.zb[0])[None])
    idx_c, logf_c = jnp.asarray(cur.idx)[None], jnp.asarray(cur.logf)[None]
    cost, moved = cur.cost, False
    size = _few_size(1, *sized)
    for _ in range(MAX_REFINEMENTS):
        out, c2, s2 = _fit_batch(
            joint, _pad(v, size), _pad(idx_c, size), _pad(logf_c, size), superset.sigma_j, state.step, max_steps
        )
        c2 = float(np.asarray(c2)[0])
        if not (np.isfinite(c2) and c2 < cost):
            break
        gained = N * math.log(cost / max(c2, 1e-300))
        v = jax.tree_util.tree_map(lambda a: jnp.asarray(a)[:1], out)
        cost, moved = c2, True
        if gained < 0.1 or int(np.asarray(s2)[0]) < max_steps:
            break
    if not moved or N * math.log(cur.cost / max(cost, 1e-300)) < 0.1:
        return cur
    options.say(f"  the accepted model refitted alone: cost {cur.cost:.6g} -> {cost:.6g}")
    v1 = v.take(0)
    theta = superset.theta_of(v1, np.asarray(cur.idx), np.asarray(cur.logf))
    return dataclasses.replace(cur, v=v1, cost=cost, ho=held.residuals(theta[None], state.step)[0])
