"""Episodes and actions to a threshold as time to an event.

A session that reached a threshold did so after a number of episodes (or actions); one that
never did was watched for as many as its last evaluation counts and then stopped: its time to
the threshold is *censored* there, known only to be longer. Averaging the sessions that
reached it (the paper's Welch t-tests) leaves the others out and so conditions on success;
here every taught session counts.

- ``kaplan_meier``: the share of a learner's sessions that have not reached the threshold
  after each count (statsmodels' ``SurvfuncRight``), with the median count and its 95%
  interval (the complementary log-log method);
- ``cox_stratified``: a Cox proportional hazards model (statsmodels' ``PHReg``, Efron's
  method for tied counts) of the baseline's and one alternative's sessions, stratified by
  block (one participant in one environment) with the session's position in the
  participant's order as a covariate. Its hazard ratio is how many times faster, per episode
  still to go, the alternative's sessions reach the threshold than the baseline's of the same
  participant: below 1 the alternative is slower.

Sessions without evaluations were never watched and are left out.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.design import Z95
from analysis.names import learner_display
from analysis.stats import reached_column, required_column

# A Cox fit converges in a few Newton steps; one that has not in 30 is separated (the
# coefficient grows without bound), and so is one whose standard error exceeds 20 on the log
# scale.
MAX_ITERATIONS = 30
MAX_SE = 20.0


def event_times(
    summary: pd.DataFrame, evaluations: pd.DataFrame, measure: str, threshold: float
) -> pd.DataFrame:
    """One row per taught session: ``time`` is the count of ``measure`` ("episodes" or
    "actions") at which it first reached ``threshold`` (``event`` True), or else the count at
    its last evaluation (``event`` False, censored)."""
    last = evaluations.groupby("session_id")[measure].max()
    taught = summary.loc[summary["evaluations"] > 0]
    event = taught[reached_column(threshold)].astype(bool)
    reached_at = taught[required_column(measure, threshold)].astype(float)
    time = np.where(event, reached_at, taught["session_id"].map(last).astype(float))
    frame = taught.loc[:, ["participant_id", "environment", "learner", "position"]].copy()
    frame["time"] = time
    frame["event"] = event.to_numpy()
    return frame.reset_index(drop=True)


@dataclass(frozen=True)
class Median:
    sessions: int
    events: int
    median: float  # NaN when fewer than half the sessions reached the threshold
    low: float
    high: float  # inf when the interval is open above


def kaplan_meier(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """The Kaplan-Meier estimate of the share not yet at the threshold: the distinct event
    counts and the estimate just after each (empty without events)."""
    from statsmodels.duration.survfunc import SurvfuncRight

    if not frame["event"].any():
        return np.array([]), np.array([])
    curve = SurvfuncRight(frame["time"].to_numpy(float), frame["event"].to_numpy(int))
    return np.asarray(curve.surv_times, float), np.asarray(curve.surv_prob, float)


def median_time(frame: pd.DataFrame) -> Median:
    """The median count to the threshold (statsmodels' ``quantile``: the first count at which
    the Kaplan-Meier estimate falls below 1/2; where it equals 1/2 over an interval, R's
    ``survfit`` takes the interval's midpoint instead) and its 95% interval (statsmodels' ``quantile_ci``, complementary
    log-log)."""
    from statsmodels.duration.survfunc import SurvfuncRight

    sessions, events = len(frame), int(frame["event"].sum())
    nan = float("nan")
    if events == 0:
        return Median(sessions, 0, nan, nan, nan)
    curve = SurvfuncRight(frame["time"].to_numpy(float), frame["event"].to_numpy(int))
    median = float(curve.quantile(0.5))
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        low, high = (float(v) for v in curve.quantile_ci(0.5, method="cloglog"))
    if not np.isfinite(median):
        median = nan
    return Median(sessions, events, median, low, high)


@dataclass(frozen=True)
class HazardRatio:
    ratio: float | None
    low: float | None
    high: float | None
    p_value: float | None
    blocks: int
    note: str = ""


def cox_stratified(frame: pd.DataFrame, baseline: str, alternative: str) -> HazardRatio:
    """The stratified Cox model of the baseline's and the alternative's sessions (see the
    module's docstring); the hazard ratio is the alternative's over the baseline's, with its
    Wald 95% interval and p-value. Only blocks with a session of both count."""
    from statsmodels.duration.hazard_regression import PHReg

    pair = frame.loc[frame["learner"].isin([baseline, alternative])]
    strata = pair["participant_id"].astype(str) + "\x1f" + pair["environment"].astype(str)
    both = pair.groupby(strata)["learner"].transform("nunique") == 2
    pair, strata = pair.loc[both], strata.loc[both]
    blocks = int(strata.nunique())
    for name in (baseline, alternative):
        if not pair.loc[pair["learner"] == name, "event"].any():
            return _not_estimated(
                blocks,
                f"no {learner_display(name)} session reached it in a "
                "block with both learners: the hazard ratio cannot be estimated",
            )
    if _one_sided(pair, strata, alternative):
        return _not_estimated(
            blocks,
            "in every block one learner's session reached it first (or alone): the hazard "
            "ratio is 0 or infinite, not estimable",
        )
    exog = np.column_stack(
        [(pair["learner"] == alternative).to_numpy(float), pair["position"].to_numpy(float)]
    )
    if np.ptp(exog[:, 1]) == 0:
        exog = exog[:, :1]
    from statsmodels.tools.sm_exceptions import ConvergenceWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            fit = PHReg(
                pair["time"].to_numpy(float),
                exog,
                status=pair["event"].to_numpy(int),
                strata=strata.to_numpy(),
                ties="efron",
            ).fit(maxiter=MAX_ITERATIONS)
        except (np.linalg.LinAlgError, ValueError) as error:
            return _not_estimated(blocks, f"the model failed: {error}")
    coefficient, se = float(fit.params[0]), float(fit.bse[0])
    converged = not any(issubclass(w.category, ConvergenceWarning) for w in caught)
    if not (converged and math.isfinite(coefficient) and math.isfinite(se)) or se > MAX_SE:
        return _not_estimated(
            blocks,
            "the estimate does not converge: the hazard ratio runs off to 0 or infinity, as "
            "when one learner's session reaches it first in every block where either did",
        )
    from scipy.stats import norm

    p_value = float(2 * norm.sf(abs(coefficient / se)))
    return HazardRatio(
        math.exp(coefficient),
        math.exp(coefficient - Z95 * se),
        math.exp(coefficient + Z95 * se),
        p_value,
        blocks,
    )


def _not_estimated(blocks: int, note: str) -> HazardRatio:
    return HazardRatio(None, None, None, None, blocks, note)


def _one_sided(pair: pd.DataFrame, strata: pd.Series, alternative: str) -> bool:
    """Whether only one learner ever reached the threshold while a session of the other was
    still going in its block: then the partial likelihood grows without bound as the
    learner's coefficient does, whatever the other covariates, and has no maximum."""
    wins = set()
    for _, block in pair.groupby(strata.to_numpy()):
        time = block["time"].to_numpy(float)
        event = block["event"].to_numpy(bool)
        is_alternative = (block["learner"] == alternative).to_numpy()
        for i in np.flatnonzero(event):
            other = is_alternative != is_alternative[i]
            # Still going: later, or censored at the same count (a tie of events is neither).
            going = other & ((time > time[i]) | ((time == time[i]) & ~event))
            if going.any():
                wins.add(bool(is_alternative[i]))
        if len(wins) == 2:
            return False
    return True
