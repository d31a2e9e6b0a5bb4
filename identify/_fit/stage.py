"""`Stage`: one Levenberg-Marquardt solve of a fit (a horizon stage or the multi-start stage)."""

from __future__ import annotations

import dataclasses

import optimistix as optx

from .levenberg_marquardt import _result_name


@dataclasses.dataclass(frozen=True)
class Stage:
    """One solve of a fit, as `FitResult.stages` lists them.

    - `horizon_s`: the horizon (s from each log's onset) the solve fitted;
    - `iterations`: Levenberg-Marquardt steps taken (the most of any start's, for the
      multi-start stage);
    - `cost`: its final cost, `0.5 sum r^2` of the noise-weighted residuals;
    - `result`: optimistix's outcome (`optx.RESULTS`), kept as such; `outcome` names it;
    - `starts`, `start_costs`: for the multi-start stage, how many starts were solved and
      each one's final cost (`None` otherwise);
    - `segments`: for a multiple-shooting solve (`fit(..., shooting="multiple")`), the
      number of segments the logs were cut into, its `cost` that of the output residuals
      alone (`None` otherwise)."""

    horizon_s: float
    iterations: int
    cost: float
    result: optx.RESULTS
    starts: int | None = None
    start_costs: tuple[float, ...] | None = None
    segments: int | None = None

    @property
    def outcome(self) -> str:
        """`"successful"`, `"max_steps_reached"` (the step budget ran out) or `"failed"`."""
        return _result_name(self.result)

    def to_dict(self) -> dict:
        """The stage as `result.json` writes it (`result` as `outcome`)."""
        out = {"horizon_s": self.horizon_s, "iterations": self.iterations, "cost": self.cost, "result": self.outcome}
        if self.starts is not None:
            out["starts"] = self.starts
            out["start_costs"] = list(self.start_costs)
        if self.segments is not None:
            out["segments"] = self.segments
        return out
