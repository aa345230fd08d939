"""A model of success at a threshold that knows whose sessions they are.

The method, pinned: generalized estimating equations (statsmodels' ``GEE``) of a logistic
model, ``reached ~ C(learner) + C(environment) + position`` over all environments and
``reached ~ C(learner) + position`` within one, fitted to the sessions of the baseline and one
alternative at a time (the baseline is the reference level),
``position`` the session's place in the participant's order (0-5) as a linear term; the
sessions are clustered on the participant with an exchangeable working correlation, and the
standard errors are the bias-reduced sandwich of Mancl and DeRouen (2001,
``cov_type="bias_reduced"``), which keeps its level with few participants better than the plain
robust one. The odds ratios are population averaged: the odds of success for the alternative
against the baseline in a typical session of the same environment and position.

A learner whose sessions all reached the threshold, or none did, makes the odds ratio infinite
or zero (separation): the model is not fitted and a note says why.
"""

from __future__ import annotations

import math
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.design import Z95
from analysis.names import learner_display, order_environments
from analysis.stats import reached_column

METHOD = (
    "GEE, logit link, exchangeable working correlation within participant, "
    "bias-reduced sandwich errors (Mancl-DeRouen)"
)


@dataclass(frozen=True)
class OddsRatio:
    ratio: float | None
    low: float | None
    high: float | None
    p_value: float | None
    note: str = ""


def gee_odds_ratios(
    summary: pd.DataFrame,
    threshold: float,
    baseline: str,
    alternatives: Sequence[str],
    *,
    pooled: bool,
) -> dict[str, OddsRatio]:
    """Each alternative's odds ratio of success against the baseline, from a model of the
    two learners' sessions in ``summary`` (``pooled``: over several environments, with
    environment as a factor). See the module's docstring."""
    data = pd.DataFrame(
        {
            "reached": summary[reached_column(threshold)].astype(float).to_numpy(),
            "learner": summary["learner"].to_numpy(),
            "environment": summary["environment"].to_numpy(),
            "position": summary["position"].astype(float).to_numpy(),
            "participant": summary["participant_id"].to_numpy(),
        }
    )
    return {
        name: _pair(data.loc[data["learner"].isin([baseline, name])], baseline, name, pooled)
        for name in alternatives
    }


def _pair(data: pd.DataFrame, baseline: str, alternative: str, pooled: bool) -> OddsRatio:
    notes = []
    if pooled:
        # An environment where every session, or none, reached the threshold says nothing
        # about the learners and would make its own coefficient infinite.
        rate = data.groupby("environment")["reached"].transform("mean")
        uninformative = (rate == 0) | (rate == 1)
        if uninformative.any():
            left = sorted(data.loc[uninformative, "environment"].unique())
            notes.append(f"left out {', '.join(left)} (every session or none reached it)")
            data = data.loc[~uninformative]
    if data.empty:
        return _none("in every environment every session reached it, or none did")
    rates = data.groupby("learner")["reached"].mean()
    for name in (baseline, alternative):
        if name not in rates.index:
            return _none(f"no {learner_display(name)} sessions")
    separated = [name for name in (baseline, alternative) if rates[name] in (0.0, 1.0)]
    if separated:
        return _none(
            "; ".join(
                f"{'every' if rates[n] == 1 else 'no'} {learner_display(n)} session reached it"
                for n in separated
            )
            + " (separation: the odds ratio is not finite)"
        )
    if data["participant"].nunique() < 2:
        return _none("fewer than 2 participants")
    return _fit(data, baseline, alternative, pooled, "; ".join(notes))


_LARGEST_LOG = math.log(sys.float_info.max)  # about 709.8


def _none(note: str) -> OddsRatio:
    return OddsRatio(None, None, None, None, note)


def _fit(data: pd.DataFrame, baseline: str, alternative: str, pooled: bool, note: str) -> OddsRatio:
    import statsmodels.api as sm
    from scipy.stats import norm

    # The design matrix, built by hand (a formula's parsing costs more than the fit): an
    # intercept, the alternative's indicator, then the environments' (the first in the
    # paper's order is the reference) and the position.
    columns = [np.ones(len(data)), (data["learner"] == alternative).to_numpy(float)]
    if pooled:
        for environment in order_environments(data["environment"])[1:]:
            columns.append((data["environment"] == environment).to_numpy(float))
    if data["position"].nunique() > 1:
        columns.append(data["position"].to_numpy(float))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            fit = sm.GEE(
                data["reached"].to_numpy(float),
                np.column_stack(columns),
                groups=data["participant"].to_numpy(),
                family=sm.families.Binomial(),
                cov_struct=sm.cov_struct.Exchangeable(),
            ).fit(cov_type="bias_reduced", maxiter=100)
        except (np.linalg.LinAlgError, ValueError) as error:
            return _none(f"the model failed: {error}")
    coefficient, se = float(fit.params[1]), float(fit.bse[1])
    if not (math.isfinite(coefficient) and math.isfinite(se) and se > 0):
        return _none("the model did not converge")
    if abs(coefficient) + Z95 * se > _LARGEST_LOG:
        # A near-separation the counts above miss (a covariate's level, the position): the
        # interval's bound is not a float.
        return _none("the model did not converge (the odds ratio's interval is unbounded)")
    return OddsRatio(
        math.exp(coefficient),
        math.exp(coefficient - Z95 * se),
        math.exp(coefficient + Z95 * se),
        float(2 * norm.sf(abs(coefficient / se))),
        note,
    )
