"""The records `diagnose_logs` passes between its phases: what the logs drive (`Signals`), the
search's options (`SearchOptions`), the model it stands at (`CurrentModel`), a round's fits
(`CandidateFits`, `StructuralModel`), and what the rounds have found so far (`SearchState`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np

import flexdyn as fd

from .._data import measurement as meas
from .._fit.result import FitResult
from .._model.problem import Problem
from . import catalogue as cat
from .joint_model import JointVariables
from .scores import Score


@dataclasses.dataclass(frozen=True)
class Signals:
    """What the fit logs drive and how fast, for the catalogue's starting values and limits."""

    driven: list[int]  # the joints with a non-zero torque in some log
    sample_interval: float  # the fit logs' median sample interval, s
    torque_rms: float  # RMS applied torque over the fit logs, N m
    torque_peak: float  # largest |applied torque| over the fit logs, N m
    rate_rms: float  # RMS rate of the first link angle channel, rad/s (1 without one)
    offsets_fitted: set[str]  # channels whose offset every fit log estimates
    positive_modes: list[float]  # the baseline's modal frequencies above 0, Hz
    # the structural guesses' frequency: 2x the highest mode, at most Nyquist (Hz)
    max_frequency_hz: float
    stiffening_links: set[str]  # links the model check flags for geometric stiffening
    log_duration: float  # the shortest fit log's duration, s

    @property
    def nyquist_hz(self) -> float:
        return 0.5 / self.sample_interval

    def plausibility(self, chain: fd.Chain) -> cat.Plausibility:
        """What a candidate's fitted values on the fitted rig `chain` are judged against
        (`catalogue.Plausibility`): the torque scale of its peak torque, the shortest fit
        log, the lowest mode, the links' lengths."""
        return cat.Plausibility(
            torque_scale=cat.characteristic_torque(chain, self.torque_peak),
            log_duration=self.log_duration,
            lowest_mode_hz=min(self.positive_modes) if self.positive_modes else None,
            link_lengths=tuple(float(link.length) for link in chain.links),
        )


@dataclasses.dataclass(frozen=True)
class SearchOptions:
    """`diagnose_logs`' acceptance thresholds and budgets (see its arguments), and what a
    candidate's fitted values must plausibly be on this rig to be accepted (`plausibility`)."""

    bic_threshold: float
    min_gain: float
    n_fit: int | None
    max_steps: int
    max_effects: int
    pair_search: bool
    say: Callable[[str], None]
    plausibility: cat.Plausibility


@dataclasses.dataclass(frozen=True)
class CurrentModel:
    """The model the search stands at, in the joint model (`joint_model.Superset`)."""

    v: JointVariables
    cost: float  # weighted cost on the fit logs (sum of squared residuals over the noise)
    ho: np.ndarray  # weighted held-out residuals (used entries)
    idx: np.ndarray  # (SLOTS,) each slot's extension parameter (`Superset.layout`)
    logf: np.ndarray  # (SLOTS,) whether each slot is fitted as a log
    layout: tuple = ()  # the accepted extension parameters: ((name, value, log_scale), ...) in slot order
    k: int = 0  # the parameters the accepted extensions added


@dataclasses.dataclass(frozen=True)
class CandidateFits:
    """A round's continuous fits (`continuous.score_continuous`): the variables of every
    start (`vs`, batch-first), each candidate's best start (`best`: label -> row), the
    starts' slot layouts (`idx`, `logf`), the weighted held-out residuals of the fitted
    candidates' best starts (`ho`, rows in `labels` order), and `size`, the batch size and the
    seconds its call took (`joint_model._few_size`)."""

    vs: JointVariables  # batch-first
    best: dict
    idx: jax.Array
    logf: jax.Array
    ho: np.ndarray
    labels: list
    size: tuple[int, float]

    def variables(self, label: str) -> JointVariables:
        """The variables of `label`'s best start."""
        return self.vs.take(self.best[label])

    def held_out_residual(self, label: str) -> np.ndarray:
        return self.ho[self.labels.index(label)]


@dataclasses.dataclass(frozen=True)
class StructuralModel:
    """A structural candidate's fitted model (`structural._structural_score`)."""

    chain: fd.Chain
    measurement: meas.Measurement
    parameters: list  # its free `Parameter`s, guesses at their fitted values
    fit: FitResult
    held_out_cost: float  # weighted cost on the held-out logs
    held_out_problem: Problem
    held_out_residual: np.ndarray  # weighted held-out residuals (used entries)


@dataclasses.dataclass(frozen=True)
class Accepted:
    """An accepted catalogue entry and the score it was accepted with (a pair's for both members)."""

    candidate: cat.Candidate
    score: Score
    together_with: list[str] = dataclasses.field(default_factory=list)  # the pair's other member


@dataclasses.dataclass(frozen=True)
class StackOn:
    """An accepted structural change: the search goes on from its model (`diagnosis._stacked`)."""

    model: StructuralModel
    rounds_used: int
    promising: set  # the structural candidates worth fitting again from that model


@dataclasses.dataclass
class SearchState:
    """What the rounds of one search change (host-side, mutated by the phases)."""

    current: CurrentModel
    step: jax.Array | float  # the constant integration step, made finer where needed (`_finer_step`)
    notes: list  # `Diagnosis.notes`
    round: int = 0  # the round under way, from 0
    accepted: list[Accepted] = dataclasses.field(default_factory=list)
    rounds: list[list[Score]] = dataclasses.field(default_factory=list)  # each round's scores, best first
    causes_scores: list[Score] = dataclasses.field(default_factory=list)  # each round's winner
    screen_batch: int | None = None  # the first screening's batch size (later ones reuse its program)
    struct_promising: set = dataclasses.field(default_factory=set)  # structural labels to fit this round
    # structural label -> (cost drop when last fitted, k), and its model fitted this round
    struct_drop: dict = dataclasses.field(default_factory=dict)
    struct_models: dict[str, StructuralModel] = dataclasses.field(default_factory=dict)
    stack_on: StackOn | None = None  # a structural winner: the search goes on from its model
    # the baseline refitted from a candidate's optimum before any cause was accepted (`own_gain`)
    refitted_baseline: CurrentModel | None = None

    @property
    def done(self) -> set[str]:
        """The labels of the accepted entries."""
        return {a.candidate.label for a in self.accepted}
