"""`diagnose_logs`: the search over the catalogue, round by round, for the extension that explains
the residual and predicts the held-out data. An orchestrator of named phases over a `SearchState`:
the baseline fit, the signals the logs carry, the candidates offered, the joint model and the
held-out logs on it, the rounds (continuous candidates, structural ones, pairs, acceptance), the
assembly of the `Diagnosis`, and the search from an accepted structural model stacked on it.
"""

from __future__ import annotations

import dataclasses
import time

import jax.numpy as jnp
import numpy as np

import flexdyn as fd

from .._data import measurement as meas
from .._fit.fit import fit
from .._fit.result import FitResult, fitted_outputs
from .._model.parameters import Parameter
from .._model.problem import make_problem
from . import catalogue as cat, evidence as ev, own_gain
from .continuous import pair_search, reconverge, score_continuous
from .diagnosis import Diagnosis, _stacked, _with_totals, assemble
from .held_out import HeldOutSet, _with_extra_state, held_out_set
from .joint_model import SLOTS, JointVariables, Superset, superset_of
from .notes import CLOSED_LOOP_NOTE, _baseline_notes, _convergence_notes, _fits_but_does_not_predict, _not_tried
from .scores import round_verdicts
from .state import Accepted, CurrentModel, SearchOptions, SearchState, Signals
from .structural import _StructuralFits, fit_structural_round, promising_next, record_drops, stack_on_structural


def _modal_frequencies(chain: fd.Chain) -> list[float]:
    try:
        return fd.natural_frequencies(chain)[0]
    except Exception:  # a rig without a stable equilibrium has no modal table
        return []


def diagnose_logs(
    chain: fd.Chain,
    parameters,
    fit_logs,
    held_out_logs,
    noise: dict | None = None,
    *,
    split: str = "",
    catalogue=cat.NAMES,
    exclude=(),
    measurement: meas.Measurement | None = None,
    controller=None,
    max_effects: int = 3,
    pair_search: bool = True,
    bic_threshold: float = 10.0,
    min_gain: float = 1.1,
    max_steps: int = 25,
    n_fit: int | None = 3,
    rtol: float = 1e-8,
    fit_options: dict | None = None,
    progress=None,
) -> Diagnosis:
    """Diagnose in-memory logs (`LogData`); see the module docstring. `parameters` are the
    baseline's free `Parameter`s; `noise` maps channels to known standard deviations;
    `measurement` is the baseline's sensor and actuator model (default: ideal);
    `controller` (`identify.Controller`): the logs are closed-loop, run under this law
    (every candidate's model simulates the loop: `make_problem`'s `controller`).
    `catalogue` names the entries to try; `exclude` lists candidate labels not to try
    (`name:where`, e.g. `coulomb_friction:joint1`).

    Ctrl-C (`KeyboardInterrupt`) during the search rounds ends the search there: the
    diagnosis of what was accepted before it is returned, with `Diagnosis.interrupted`
    saying where it stopped (a diagnosis of hours must not be lost to a job's time limit).
    Before the rounds (the baseline fit, the set-up) it propagates: there is nothing to report."""
    start = time.perf_counter()
    say = progress or (lambda msg: None)
    _check_arguments(catalogue, exclude, held_out_logs)
    noise = dict(noise or {})
    parameters = list(parameters)
    # the baseline misses an effect on purpose: no restarts for its poor fit (`fit`)
    # `grid_error=None`: the tight integration step (`identify.fit.GRID_ERROR`), which the
    # candidates' fits reuse: a candidate's fit moves into stiffer models (dry friction is a
    # stiff damper at rest) than the baseline's optimum at which a coarser step would be checked.
    fit_options = {"restart_poor_fit": False, "grid_error": None, **(fit_options or {})}
    say("baseline fit ...")
    measurement = meas.Measurement() if measurement is None else measurement
    base = _baseline_fit(chain, parameters, fit_logs, noise, measurement, controller, rtol, fit_options, progress)
    channels = base.problem.channels
    sigma = np.asarray([base.sigma[c] for c in channels])
    notes = _baseline_notes(base.names, base.std_errors, base.values)  # `Diagnosis.notes`
    notes += _convergence_notes(base.stages[-1].outcome, base.at_bounds)
    if controller is not None:
        notes.append({"round": 0, "text": CLOSED_LOOP_NOTE})
    for n in notes:
        say(f"  warning: {n['text']}")
    modal = _modal_frequencies(base.chain)
    signals = _signals(base, fit_logs, held_out_logs, modal)
    options = SearchOptions(
        bic_threshold, min_gain, n_fit, max_steps, max_effects, pair_search, say, signals.plausibility(base.chain)
    )
    cands, not_tried = _candidates(base, parameters, signals, catalogue, exclude)
    superset = superset_of(
        chain,
        measurement,
        channels,
        signals.driven,
        cands,
        parameters,
        fit_logs,
        sigma,
        len(base.problem.names),
        controller=controller,
    )
    # held-out batches are padded to one size, so that every round reuses the compiled program
    held = held_out_set(superset, held_out_logs, channels, base, (n_fit or len(cands)) + 1, max_steps)
    baseline = _baseline_model(superset, held, base, say)
    state = SearchState(current=baseline, step=base.step, notes=notes)
    structural = _structural_setting(base, parameters, superset, fit_logs, held_out_logs, signals, rtol, options)
    interrupted = _rounds(superset, held, options, structural, state, cands, signals)
    # a baseline refitted in the rounds (`own_gain`) is the baseline the causes are scored against
    baseline = state.refitted_baseline or baseline
    diag = _assembled(
        interrupted,
        split=split,
        options=options,
        base=base,
        superset=superset,
        held=held,
        baseline=baseline,
        state=state,
        cands=cands,
        modal=modal,
        not_tried=not_tried,
    )
    if state.stack_on is not None and interrupted is None:
        inner = _search_on(
            state,
            cands,
            fit_logs,
            held_out_logs,
            dict(zip(channels, sigma)),
            options,
            controller=controller,
            split=split,
            catalogue=catalogue,
            exclude=exclude,
            rtol=rtol,
            fit_options=fit_options,
            progress=progress,
        )
        diag = _stacked(diag, inner)
    return _with_totals(diag, time.perf_counter() - start)


def _rounds(superset, held, options, structural, state: SearchState, cands, signals) -> str | None:
    """The search rounds (`_round`), until one accepts nothing or `max_effects` are named;
    after Ctrl-C, where the search stopped (else None)."""
    for rnd in range(options.max_effects):
        state.round = rnd
        try:
            if not _round(superset, held, options, structural, state, cands, signals):
                return None
        except KeyboardInterrupt:
            text = (
                f"interrupted (Ctrl-C) in round {rnd + 1}, after {len(state.accepted)} cause(s) accepted; "
                "the search did not finish"
            )
            options.say(f"  {text}: reporting what was accepted before it")
            return text
    return None


def _assembled(interrupted: str | None, **parts) -> Diagnosis:
    """`assemble(**parts)`, marked `interrupted`; a diagnosis that cannot be assembled after an
    interruption (its state left half-way) ends as the interruption it is."""
    if interrupted is None:
        return assemble(**parts)
    try:
        diag = assemble(**parts)
    except Exception:  # noqa: BLE001 (a round stopped mid-way: nothing consistent to report)
        raise KeyboardInterrupt from None
    return dataclasses.replace(diag, interrupted=interrupted)


def _check_arguments(catalogue, exclude, held_out_logs) -> None:
    """Refuse unknown catalogue names or candidate labels, and a search without held-out data."""
    unknown = set(catalogue) - set(cat.NAMES)
    if unknown:
        raise ValueError(f"diagnose: unknown catalogue entries {sorted(unknown)}; the catalogue has {list(cat.NAMES)}")
    for label in exclude:
        if str(label).split(":", 1)[0] not in cat.NAMES:
            raise ValueError(
                f"diagnose: exclude: {label!r} is not a candidate label (name:where, e.g. 'coulomb_friction:joint1'; "
                f"the names are {list(cat.NAMES)})"
            )
    if not held_out_logs:
        raise ValueError("diagnose: no held-out data (give validation logs, or at least one log to split)")


def _baseline_fit(
    chain, parameters, fit_logs, noise, measurement, controller, rtol, fit_options, progress
) -> FitResult:
    """The baseline model fitted to the fit logs, the noise of the channels without a known
    one (`noise`) estimated from its residuals."""
    problem = make_problem(
        chain,
        parameters,
        fit_logs,
        noise,
        rtol=rtol,
        atol=1e-2 * rtol,
        measurement=measurement,
        controller=controller,
    )
    estimate = [c for c in problem.channels if noise.get(c) is None]
    return fit(problem, parameters, estimate_noise=estimate or False, progress=progress, **fit_options)


def _signals(base: FitResult, fit_logs, held_out_logs, modal) -> Signals:
    """What the logs drive and how fast (`Signals`), at the baseline fit `base` (modal
    frequencies `modal`, Hz)."""
    channels, fitted_chain = base.problem.channels, base.chain
    driven = sorted(
        {
            j
            for log in list(fit_logs) + list(held_out_logs)
            if log.torque is not None
            for j in range(np.asarray(log.torque).reshape(len(log.t), -1).shape[1])
            if np.any(np.asarray(log.torque).reshape(len(log.t), -1)[:, j] != 0)
        }
    )
    t0 = np.asarray(fit_logs[0].t, float)
    dt_sample = float(np.median(np.diff(t0)))
    torques = np.concatenate(
        [np.asarray(log.torque, float).ravel() for log in fit_logs if log.torque is not None] or [np.zeros(1)]
    )
    torque_rms, torque_peak = float(np.sqrt(np.mean(torques**2))), float(np.max(np.abs(torques)))
    rate_rms = 1.0
    for c in channels:
        if c.startswith("theta") or c.startswith("alpha"):
            rate_rms = float(
                np.sqrt(
                    np.mean(
                        [
                            np.mean(np.gradient(np.asarray(log.outputs[c]), np.asarray(log.t)) ** 2)
                            for log in fit_logs
                            if c in log.outputs
                        ]
                    )
                )
            )
            break
    offsets_fitted = {c for c in channels if all(c in log.offsets for log in fit_logs if c in log.outputs)}
    # the frequency a structural guess aims at: 2x the model's highest mode, at most Nyquist
    # (a joint mode far above it stiffens the problem for nothing; the structural fit's
    # multi-start covers a factor 3 in stiffness either side)
    positive_modes = [f for f in modal if f > 0]
    max_f = min(0.5 / dt_sample, 2.0 * max(positive_modes)) if positive_modes else 0.5 / dt_sample
    # geometric stiffening is offered where the model check (on every log, at the end) would
    # flag it from the baseline's motion on the fit logs
    stiffening_links = set()
    if any(link.n_modes > 0 and not link.geometric_stiffening for link in fitted_chain.links):
        stiffening_links = {
            check["link"]
            for check in ev.stiffening_checks_of(fitted_chain, fitted_outputs(base), key="simulated")
            if check["flagged"]
        }
    log_duration = min(float(np.ptp(np.asarray(log.t, float))) for log in fit_logs)
    return Signals(
        driven,
        dt_sample,
        torque_rms,
        torque_peak,
        rate_rms,
        offsets_fitted,
        positive_modes,
        max_f,
        stiffening_links,
        log_duration,
    )


def _candidates(base: FitResult, parameters, signals: Signals, catalogue, exclude) -> tuple[list, dict]:
    """The catalogue's candidates to try on the fitted rig (`catalogue.candidates`: those
    named in `catalogue`, not excluded, and whose parameters are not free in the baseline
    already), and why each entry without one was not tried (`Diagnosis.not_tried`), and each
    sensor entry a channel's sensor kind rules out (`catalogue.kind_left_out`)."""
    fitted_chain = base.chain
    kinds = meas.kinds(base.problem.measurement)
    offered = cat.candidates(
        fitted_chain,
        base.problem.channels,
        signals.driven,
        torque_rms=signals.torque_rms,
        rate_rms=signals.rate_rms,
        sample_interval=signals.sample_interval,
        channel_rms={},
        offsets_fitted=signals.offsets_fitted,
        max_frequency_hz=signals.max_frequency_hz,
        stiffening_links=signals.stiffening_links,
        sensor_kinds=kinds,
    )
    free = {p.name for p in parameters}
    cands = [c for c in offered if c.name in catalogue and c.label not in exclude and not set(c.params) & free]
    inapplicable = cat.not_applicable(fitted_chain, signals.driven, signals.stiffening_links)
    by_kind = cat.kind_left_out(base.problem.channels, kinds, signals.offsets_fitted)
    return cands, _not_tried(catalogue, offered, cands, exclude, inapplicable, by_kind)


def _baseline_model(superset: Superset, held: HeldOutSet, base: FitResult, say) -> CurrentModel:
    """The baseline in the joint model (every extension neutral): the same model, so the same
    cost as its fit; its held-out residual."""
    idx0, logf0, _ = superset.layout([])
    v_base = JointVariables(
        offset=jnp.asarray(base.z.offset),
        xe=jnp.zeros(SLOTS),
        y0=jnp.asarray(base.z.y0),
        zb=jnp.asarray(base.z.phys),
    )
    theta_base = superset.theta_of(v_base, idx0, logf0)
    cost0 = float(base.cost)
    ho0 = held.residuals(theta_base[None], base.step)[0]
    say(f"baseline: cost {cost0:.6g} over {superset.N} residuals; held-out weighted RMS {np.sqrt(np.mean(ho0**2)):.4g}")
    return CurrentModel(v_base, cost0, ho0, idx0, logf0)


def _structural_setting(
    base: FitResult, parameters, superset: Superset, fit_logs, held_out_logs, signals: Signals, rtol, options
) -> _StructuralFits:
    """What every structural candidate's fit in this search shares (`structural._StructuralFits`)."""
    return _StructuralFits(
        base,
        parameters,
        superset.measurement,
        superset.controller,
        list(fit_logs),
        list(held_out_logs),
        base.problem.channels,
        superset.sigma,
        superset.N,
        rtol,
        options.bic_threshold,
        options.min_gain,
        signals.max_frequency_hz,
        signals.nyquist_hz,
        options.say,
        options.plausibility,
    )


def _round(
    superset: Superset,
    held: HeldOutSet,
    options: SearchOptions,
    structural: _StructuralFits,
    state: SearchState,
    cands,
    signals: Signals,
) -> bool:
    """Round `state.round`: the continuous candidates not accepted yet, the structural ones,
    the pairs; the best that passes both tests is accepted. Returns whether the search goes
    on in the joint model."""
    done = state.done
    remaining = [c for c in cands if c.label not in done and not c.structural]
    if not remaining:
        return False
    scores, fits = _continuous_round(superset, held, options, state, remaining)
    fit_structural_round(structural, state, cands, scores, fits, held.problem)
    pairs, pair_fits = [], None
    if options.pair_search:
        pairs, pair_scores, pair_fits = pair_search(superset, held, options, state, cands, remaining, scores, fits)
        scores.extend(pair_scores)
    scores.sort(key=_rank)
    state.rounds.append(scores)
    record_drops(state, scores, cands)
    _say_scores(scores, options.say)
    winners = [s for s in scores if s.accepted]
    _note_implausible(scores, winners, state, options.say)
    if not winners:
        hint = _fits_but_does_not_predict(scores, options.bic_threshold, options.min_gain, signals.offsets_fitted)
        if hint:
            options.say(f"  round {state.round + 1}: {hint}")
            state.notes.append({"round": state.round + 1, "text": hint})
        return False
    winner = winners[0]
    if winner.members:
        candidate, fits = next(p for p in pairs if p.label == winner.label), pair_fits
    else:
        candidate = next(x for x in cands if x.label == winner.label)
    return _accept(superset, held, options, structural, state, winner, candidate, fits)


def _continuous_round(superset: Superset, held: HeldOutSet, options: SearchOptions, state: SearchState, remaining):
    """The round's continuous candidates `remaining` scored (`score_continuous`) against a
    current model that does not hand them its own gain: when the round's leading candidate's
    gain is the current model's (`own_gain.refitted_if_not_own`), that model is refitted and
    they are scored again (at most `own_gain.MAX_REFITS` times), then with every candidate
    the screening finds promising fitted (no `n_fit` cut): the screening's one-step
    predictions come from a model just found stuck, and on the flexible servo rig they
    ranked the true cause (dry friction) fourth of three fitted. The notes of a superseded
    scoring are dropped, but for a change of integration step (which stands)."""
    for _ in range(own_gain.MAX_REFITS):
        n_notes = len(state.notes)
        scores, fits = score_continuous(superset, held, options, state, remaining, state.current.v)
        refit = own_gain.refitted_if_not_own(superset, held, options, state, scores, fits)
        if refit is None:
            return scores, fits
        guard_note = state.notes[-1]
        state.notes[n_notes:] = [n for n in state.notes[n_notes:-1] if "integration step" in n["text"]] + [guard_note]
        state.current = refit
        if not state.accepted:
            state.refitted_baseline = refit
        options = dataclasses.replace(options, n_fit=None)
    return score_continuous(superset, held, options, state, remaining, state.current.v)


def _rank(s) -> tuple:
    """A round's order: by dBIC, the candidates not fitted (no dBIC) last."""
    return (bool(s.not_fitted), 0.0 if s.not_fitted else s.delta_bic)


def _note_implausible(scores, winners, state: SearchState, say) -> None:
    """A note (`Diagnosis.notes`) for each candidate of the round that passes both tests
    but is not named because its fitted values are implausible (`Score.implausible`),
    ranked above the one named (all of them when none is): what the search passed over."""
    bar = winners[0].delta_bic if winners else float("inf")
    for s in scores:
        if s.implausible and s.delta_bic < bar:
            text = (
                f"{s.label} passes both tests (dBIC {s.delta_bic:.1f}, held-out gain {s.held_out_gain:.3f}x) but is "
                f"not named: implausible: {'; '.join(s.implausible)}"
            )
            say(f"  round {state.round + 1}: {text}")
            state.notes.append({"round": state.round + 1, "text": text})


def _say_scores(scores, say) -> None:
    """The round's five best scores, as the console shows them."""
    width = max([32] + [len(s.label) for s in scores[:5]])
    verdicts = round_verdicts(scores)
    for s in scores[:5]:
        verdict = verdicts[s.label].upper() if verdicts[s.label] == "named" else verdicts[s.label]
        if s.not_fitted:
            say(f"  {s.label:<{width}} dBIC {'--':>10}  {verdict}")
            continue
        outcome = (
            f"(predicted by one Gauss-Newton step; not fitted: {s.screen_reason})"
            if s.screened
            else f"held-out gain {s.held_out_gain:6.3f}x {verdict}"
        )
        say(f"  {s.label:<{width}} dBIC {s.delta_bic:10.1f}  {outcome}")


def _accept(
    superset: Superset,
    held: HeldOutSet,
    options: SearchOptions,
    structural: _StructuralFits,
    state: SearchState,
    winner,
    candidate,
    fits,
) -> bool:
    """Accept the round's `winner` (score of `candidate`, fitted in `fits`): a continuous one
    becomes the current model, refitted alone (`reconverge`) when rounds are left; a
    structural one ends the search in the joint model (`stack_on_structural`). Returns
    whether the search goes on in the joint model."""
    for m in candidate.members or (candidate,):
        state.accepted.append(Accepted(m, winner, [o.label for o in candidate.members if o is not m]))
    state.causes_scores.append(winner)
    if candidate.structural:
        stack_on_structural(structural, state, winner, candidate)
        return False
    b = fits.best[winner.label]
    added = tuple((n, winner.params[n], lg) for n, lg in zip(candidate.params, candidate.log_scale))
    state.current = CurrentModel(
        v=fits.variables(winner.label),
        cost=winner.cost,
        ho=fits.held_out_residual(winner.label),
        idx=np.asarray(fits.idx[b]),
        logf=np.asarray(fits.logf[b]),
        layout=tuple(state.current.layout) + added,
        k=state.current.k + winner.k,
    )
    if state.round + 1 < options.max_effects:
        state.current = reconverge(superset, held, options, state, fits.size)
    promising_next(structural, state, held.problem)
    return True


def _search_on(
    state: SearchState,
    cands,
    fit_logs,
    held_out_logs,
    noise: dict,
    options: SearchOptions,
    *,
    controller,
    split,
    catalogue,
    exclude,
    rtol,
    fit_options,
    progress,
) -> Diagnosis:
    """A structural change was accepted (`state.stack_on`): the search goes on from its model,
    a new baseline with every accepted effect's parameters free (its fit from the structural
    candidate's optimum, single shooting). `max_effects` counts on; with no round left the new
    baseline is only refitted: the extended model is then the structural model with every
    parameter free, its intervals from that fit."""
    model, rounds_used, promising = state.stack_on.model, state.stack_on.rounds_used, state.stack_on.promising
    say = options.say
    say(f"the search goes on from the model with {state.accepted[-1].candidate.label} ...")
    struct_chain = model.chain
    inner_params = list(model.parameters) + [Parameter(n, val) for n, val, _ in state.current.layout]
    # accepted entries are not tried again, but for one that can be applied again to its own
    # result (`catalogue.REPEATABLE`: one more mode on the link that gained one; in
    # `promising` unless the model is at the noise)
    skip = set(exclude) | {a.candidate.label for a in state.accepted if a.candidate.name not in cat.REPEATABLE}
    skip |= {c.label for c in cands if c.structural and c.label not in promising}
    return diagnose_logs(
        struct_chain,
        inner_params,
        _with_extra_state(fit_logs, struct_chain),
        _with_extra_state(held_out_logs, struct_chain),
        noise,
        measurement=model.measurement,
        controller=controller,
        split=split,
        catalogue=catalogue,
        exclude=sorted(skip),
        max_effects=options.max_effects - rounds_used,
        pair_search=options.pair_search,
        bic_threshold=options.bic_threshold,
        min_gain=options.min_gain,
        max_steps=options.max_steps,
        n_fit=options.n_fit,
        rtol=rtol,
        fit_options={
            **fit_options,
            "horizons": None,
            "n_stages": 1,
            "n_starts": 1,
            "max_restarts": 0,
            "frequency_init": False,
            "first_damping": 0.0,  # a warm start (the accepted model's values)
            "extra_starts": (),
        },
        progress=(lambda msg: say("  " + msg)) if progress else None,
    )
