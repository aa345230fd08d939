"""Writing an analysis's outputs into a folder, all or nothing."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

from analysis.design_report import describe_design_files, readme_section, write_design_outputs
from analysis.flow import ParticipantFlow
from analysis.flow_plot import save_flow
from analysis.names import threshold_label
from analysis.options import InputError
from analysis.plots import save_learning_curves
from analysis.results import Analysis
from analysis.stats import COMPARISON_COLUMNS
from analysis.tables import (
    appendix_all_latex,
    appendix_all_markdown,
    appendix_raw_latex,
    appendix_raw_markdown,
    markdown_table,
    table1_latex,
    table1_markdown,
)


def describe_outputs(analysis: Analysis) -> str:
    """The README written beside the outputs: the options, which sessions are counted, what
    each file holds, and the notes on this study's data (the same as under Table 1)."""
    if analysis.notes:
        notes = "The same notes as under Table 1:\n\n" + "".join(
            f"- {note}\n" for note in analysis.notes
        )
    else:
        notes = (
            "None: every learning session counted is of a participant who completed the study "
            "and has evaluations, and `episodes.csv` holds no empty episode.\n"
        )
    return f"""# Results of `bam-study analyze`

{describe_files(analysis.baseline, analysis.thresholds, analysis.fdr)}
{readme_section(analysis) if analysis.design is not None else ""}{flow_section(analysis.flow)}## Notes on this study's data

{notes}"""


def describe_files(baseline: str, thresholds: Sequence[float], fdr: float) -> str:
    """What the analysis counts and what each output file holds, for these options."""
    labels = ", ".join(threshold_label(t) for t in thresholds)
    return f"""Baseline learner: `{baseline}`. Thresholds (percent of the optimal total return):
{labels}. False discovery rate of the Benjamini-Yekutieli correction: {fdr:g}.

Learning sessions counted: those of the participants who completed the study (`status`
completed or submitted in `participants.csv`), as in the paper, but for those whose submission
was rejected (a decision `rejected` in `reviews.csv`, or Prolific's `REJECTED`): a rejection is
the experimenter's judgement that the work is not valid, and the paper counted the participants
who completed the study and were paid for it. `--include-rejected` counts them.
`--include-unfinished` adds
the taught sessions (at least one episode or action) of the participants who did not finish;
`--exclude-excluded` drops those of the participants the experimenter excluded, and
`--exclude-flagged` those of the participants a chosen quality check flags (`quality.csv`). A
note says
how many sessions were left out and why (returned the task, timed out, still in the study).

- `table1.md`, `table1.tex`: the paper's Table 1. Per environment and learner, the total
  learning sessions, the sessions whose normalised return reached each threshold, and the mean
  episodes and actions required (cumulative counts at the first evaluation that reached it,
  averaged over the sessions that reached it). Episodes are demonstrations plus agent
  episodes, actions the demonstrated plus the agent's; empty episodes are not counted: an
  agent's try from the goal that ended there at once (one action, `start_state` =
  `end_state`, `end_reason` goal in `episodes.csv`), which older versions of the study server
  recorded when the agent was let try on the goal. A note says how many were found, if any,
  or that no `episodes.csv` was given. `*`: significantly worse than the baseline
  (p <= 0.05); `†`: still significant after the correction. The `.tex` file needs booktabs.
- `appendix_all.md`, `appendix_all.tex`: p-values of the comparisons across all environments
  (Fisher's exact test on pooled success counts; type II ANOVA of the OLS model
  `value ~ C(learner) + C(environment) + C(position)` for episodes and actions).
- `appendix_raw.md`, `appendix_raw.tex`: raw p-values of the environment-specific comparisons
  (Fisher's exact test; Welch's t-test).
- `comparisons.csv`: one row per comparison. `scope` is an environment or `all`; `measure` is
  `success`, `episodes` or `actions`; `threshold` a fraction. `baseline_value` and
  `alternative_value` are success counts for `success` and means over the sessions that
  reached the threshold otherwise. `statistic` is the odds ratio (fisher_exact), t of
  baseline minus alternative (welch_t_test) or the learner factor's F (anova_type2).
  `p_adjusted` is the Benjamini-Yekutieli adjusted p-value over all environment-specific
  comparisons with a p-value (empty for `all`); `significant` is p <= 0.05 in either
  direction, `significant_adjusted` is p_adjusted <= the false discovery rate. `test` is
  `N/A` where a test could not be done, and `note` says why; otherwise `note` gives the
  counts and the direction of the difference.
- `sessions_summary.csv`: one row per learning session counted: its number of evaluations,
  best and final normalised return, and per threshold `reached_T`, `episodes_T` and
  `actions_T` (empty where not reached).
- `return_vs_episodes.png|svg`, `return_vs_actions.png|svg`: normalised return against the
  cumulative counts, mean and standard error per learner, one panel per environment; each
  session's latest evaluation is carried forward.
{describe_design_files()}- `participant_flow.csv`, `participant_flow.png|svg`: the participant flow, CONSORT style:
  how many arrived, consented, completed and were analysed, and at each step how many left and
  why (`kind` `left`), from `participants.csv`'s `status`, `erasures.csv`, `reviews.csv` and
  `quality.csv`. Each stage is the one above it less its `left` rows (plus its `added` row,
  with `--include-unfinished`); *analysed* is the participants and learning sessions Table 1
  counts. `counted` rows (flagged, or excluded by the experimenter, but counted all the same)
  are for information and are not subtracted. `learning_sessions` are the participants'
  learning sessions in the export (erased ones from `erasures.csv`).
"""


def flow_section(flow: ParticipantFlow | None) -> str:
    """The README's section on the participant flow: its table, and what it could not count."""
    if flow is None:
        return (
            "## Participant flow\n\nNot drawn: no `participants.csv` with a `status` column, "
            "so every learning session is counted and nothing says who left or why.\n\n"
        )
    rows = []
    for box in flow.boxes:
        label = f"**{box.label}**" if box.kind == "stage" else f"{_MARKS[box.kind]} {box.label}"
        rows.append([label, str(box.participants), str(box.learning_sessions), box.definition])
    table = markdown_table(["Stage", "Participants", "Learning sessions", "From"], rows, "lrrl")
    remarks = "".join(f"- {remark}\n" for remark in flow.remarks)
    return f"""## Participant flow

`participant_flow.csv` and `participant_flow.png|svg`. Each stage (in bold) is the one above it
less the rows marked `-` (plus the row marked `+`, with `--include-unfinished`); rows marked `=`
are counted all the same, for information.

{table}

{remarks}
"""


_MARKS = {"left": "-", "added": "+", "counted": "="}


def write_outputs(analysis: Analysis, out: Path | str) -> list[str]:
    """Write every output into ``out`` (created if needed) and return the file names.

    Everything is written into a temporary folder beside ``out`` first and moved into place
    at the end, so that a failure leaves ``out`` as it was."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} exists and is not a folder")
    texts = {
        "table1.md": table1_markdown(analysis),
        "table1.tex": table1_latex(analysis),
        "appendix_all.md": appendix_all_markdown(analysis),
        "appendix_all.tex": appendix_all_latex(analysis),
        "appendix_raw.md": appendix_raw_markdown(analysis),
        "appendix_raw.tex": appendix_raw_latex(analysis),
        "README.md": describe_outputs(analysis),
    }
    parent = out.absolute().parent
    created = _first_missing(parent)
    parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=parent))
    try:
        staging.chmod(0o777 & ~_umask())  # mkdtemp's folder is private; out should not be
        for name, text in texts.items():
            (staging / name).write_text(text, encoding="utf-8")
        analysis.summary.to_csv(staging / "sessions_summary.csv", index=False)
        analysis.comparisons.loc[:, list(COMPARISON_COLUMNS)].to_csv(
            staging / "comparisons.csv", index=False
        )
        save_learning_curves(analysis, staging)
        if analysis.design is not None:
            write_design_outputs(analysis, staging)
        if analysis.flow is not None:
            analysis.flow.frame().to_csv(staging / "participant_flow.csv", index=False)
            save_flow(analysis.flow, staging)
        names = sorted(path.name for path in staging.iterdir())
        if out.exists():
            for name in names:
                os.replace(staging / name, out / name)
            staging.rmdir()
        else:
            os.rename(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if created is not None:
            shutil.rmtree(created, ignore_errors=True)
        raise
    return names


def _first_missing(folder: Path) -> Path | None:
    """The outermost ancestor of ``folder`` (or itself) that does not exist yet."""
    missing = None
    for candidate in [folder, *folder.parents]:
        if candidate.exists():
            break
        missing = candidate
    return missing


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
