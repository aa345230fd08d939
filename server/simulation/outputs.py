"""What a run writes: ``curves.csv`` (one row per agent and round), ``summary.csv`` (mean and
standard error over agents) and ``report.md`` (settings, tables, figures, time)."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server import domains, learners
from server.simulation.config import DESCRIPTIONS, RunConfig
from server.simulation.progress import format_duration
from server.simulation.protocols import CURVE_COLUMNS, JobResult
from server.simulation.runner import atomic_write, atomic_write_text

CURVES_FILE = "curves.csv"
SUMMARY_FILE = "summary.csv"
REPORT_FILE = "report.md"

# summary.csv: one row per (experiment, environment, learner, round), over its agents.
SUMMARY_COLUMNS: tuple[str, ...] = (
    "experiment",
    "environment",
    "learner",
    "round",
    "agents",
    "mean_normalized_return",  # mean over agents of normalized_return
    "se_normalized_return",  # standard error of that mean: sd (n - 1) / sqrt(n); empty if n = 1
    "mean_total_return",
    "optimal_return",
    "mean_update_seconds",
)


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)  # repr: exact round trip
    return str(value)


def write_csv(path: Path, columns: Sequence[str], rows: Iterable[dict[str, Any]]) -> None:
    def write(temporary: Path) -> None:
        with temporary.open("w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle, lineterminator="\n")
            writer.writerow(columns)
            for row in rows:
                writer.writerow([_cell(row[column]) for column in columns])

    atomic_write(path, write)


@dataclass(frozen=True)
class SummaryRow:
    experiment: str
    environment: str
    learner: str
    round: int
    agents: int
    mean_normalized_return: float
    se_normalized_return: float
    mean_total_return: float
    optimal_return: float
    mean_update_seconds: float

    def as_dict(self) -> dict[str, Any]:
        return {column: getattr(self, column) for column in SUMMARY_COLUMNS}


def _mean_se(values: Sequence[float]) -> tuple[float, float]:
    n = len(values)
    mean = math.fsum(values) / n
    if n < 2:
        return mean, math.nan
    variance = math.fsum((v - mean) ** 2 for v in values) / (n - 1)
    return mean, math.sqrt(variance / n)


def summarize(config: RunConfig, rows: Sequence[dict[str, Any]]) -> list[SummaryRow]:
    """Mean and standard error over agents, in the run's order of environments and learners."""
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["environment"], row["learner"], int(row["round"])), []).append(row)
    summary = []
    for environment in config.environments:
        for learner in config.learners:
            for round_ in range(config.rounds + 1):
                group = groups.get((environment, learner, round_))
                if not group:
                    continue
                group = sorted(group, key=lambda r: r["agent"])
                mean, se = _mean_se([r["normalized_return"] for r in group])
                summary.append(
                    SummaryRow(
                        experiment=config.experiment,
                        environment=environment,
                        learner=learner,
                        round=round_,
                        agents=len(group),
                        mean_normalized_return=mean,
                        se_normalized_return=se,
                        mean_total_return=math.fsum(r["total_return"] for r in group) / len(group),
                        optimal_return=float(group[0]["optimal_return"]),
                        mean_update_seconds=math.fsum(r["update_seconds"] for r in group)
                        / len(group),
                    )
                )
    return summary


def ordered_curve_rows(config: RunConfig, results: Sequence[JobResult]) -> list[dict[str, Any]]:
    """Rows in the run's order: environments and learners as listed, then agent and round."""
    env_order = {name: i for i, name in enumerate(config.environments)}
    learner_order = {name: i for i, name in enumerate(config.learners)}
    rows = [row for result in results for row in result.rows]
    return sorted(
        rows,
        key=lambda r: (
            env_order[r["environment"]],
            learner_order[r["learner"]],
            r["agent"],
            r["round"],
        ),
    )


def report_rounds(rounds: int) -> list[int]:
    """The rounds the report's table shows: the start, the first rounds, the middle, the end."""
    return sorted({r for r in (0, 1, 2, rounds // 2, rounds) if 0 <= r <= rounds})


def _percent(mean: float, se: float) -> str:
    if math.isnan(se):
        return f"{100 * mean:.1f}"
    return f"{100 * mean:.1f} ± {100 * se:.1f}"


def render_report(
    config: RunConfig,
    summary: Sequence[SummaryRow],
    results: Sequence[JobResult],
    sessions: Sequence[dict[str, Any]],
    figures: Sequence[str],
    command: str,
) -> str:
    """The experiment's report in Markdown: its description, its settings (with the command
    that ran it), the results with the figures, and the time it took. One ``add`` per line of
    the report, in the order it is read, so the function is as long as the report's
    template."""
    lines: list[str] = []
    add = lines.append
    add(f"# Simulated-teacher experiment: {config.experiment}")
    add("")
    add(DESCRIPTIONS[config.experiment])
    add("")
    add(
        "Values are the agents' exact expected total return over all tasks under the true "
        "dynamics, in percent of the optimal total return (mean ± standard error over agents). "
        "Round 0 is before any data."
    )
    add("")
    add("## Settings")
    add("")
    add(f"- Command: `{command}`")
    add(f"- Experiment: {config.experiment}")
    add(f"- Environments: {', '.join(config.environments)}")
    add(
        "- Learners: "
        + ", ".join(f"{learners.DISPLAY_NAMES.get(n, n)} (`{n}`)" for n in config.learners)
    )
    add(f"- Agents per environment and learner: {config.agents}")
    add(f"- Rounds: {config.rounds}")
    add(f"- Seed: {config.seed}")
    add("- Learner settings (overrides of the defaults in **bold**):")
    for learner in config.learners:
        overrides = config.settings_of(learner)
        effective = {**learners.learner_class(learner).default_settings, **overrides}
        shown = ", ".join(
            f"**{name}={value!r}**" if name in overrides else f"{name}={value!r}"
            for name, value in sorted(effective.items())
        )
        add(f"  - `{learner}`: {shown}")
    add(
        "- Simulated teacher: hard-max value iteration on the true dynamics, ties broken at "
        "random; A-SABL feedback with epsilon 0.05, alpha 1, mu+ = mu- = 0.1."
    )
    add("")

    add("## Results")
    add("")
    rounds = report_rounds(config.rounds)
    by_key = {(row.environment, row.learner, row.round): row for row in summary}
    add("Percent of the optimal total return at selected rounds.")
    add("")
    add("| Environment | Learner | " + " | ".join(f"Round {r}" for r in rounds) + " |")
    add("|---|---|" + "---:|" * len(rounds))
    for environment in config.environments:
        for learner in config.learners:
            cells = []
            for r in rounds:
                row = by_key.get((environment, learner, r))
                cells.append(
                    "–"
                    if row is None
                    else _percent(row.mean_normalized_return, row.se_normalized_return)
                )
            add(
                f"| {domains.title(environment)} | {learners.DISPLAY_NAMES.get(learner, learner)} | "
                + " | ".join(cells)
                + " |"
            )
    add("")
    add(
        f"Every round of every agent is in `{CURVES_FILE}`; means and standard errors in `{SUMMARY_FILE}`."
    )
    add("")
    for figure in figures:
        add(f"![{config.experiment}: percent of optimal total return against rounds]({figure})")
        add("")

    add("## Time")
    add("")
    compute = math.fsum(result.seconds for result in results)
    updates = math.fsum(result.update_seconds for result in results)
    wall = math.fsum(float(session.get("seconds", 0.0)) for session in sessions)
    share = updates / compute if compute > 0 else math.nan
    add(f"- Wall time: {format_duration(wall)} ({wall:.1f} s) over {len(sessions)} session(s)")
    for session in sessions:
        add(
            f"  - {session.get('started', '?')}: {session.get('jobs_run', 0)} job(s) on "
            f"{session.get('backend', '?')} in {float(session.get('seconds', 0.0)):.1f} s"
            + (f", {session['jobs_resumed']} resumed" if session.get("jobs_resumed") else "")
        )
    add(f"- Compute time summed over jobs: {compute:.1f} s")
    add(
        f"- Of which in learner updates: {updates:.1f} s "
        f"({100 * share:.1f}%; the rest is the teacher, the episodes and the evaluation)"
    )
    add("")
    add(
        "Learner update time per round (mean seconds over agents and rounds 1 and later; the "
        "feedback experiment updates twice per round):"
    )
    add("")
    add(
        "| Environment | "
        + " | ".join(learners.DISPLAY_NAMES.get(n, n) for n in config.learners)
        + " |"
    )
    add("|---|" + "---:|" * len(config.learners))
    for environment in config.environments:
        cells = []
        for learner in config.learners:
            values = [
                row.mean_update_seconds
                for row in summary
                if row.environment == environment and row.learner == learner and row.round > 0
            ]
            cells.append(f"{math.fsum(values) / len(values):.2f}" if values else "–")
        add(f"| {domains.title(environment)} | " + " | ".join(cells) + " |")
    add("")
    return "\n".join(lines)


def write_outputs(
    out: Path,
    config: RunConfig,
    results: Sequence[JobResult],
    sessions: Sequence[dict[str, Any]],
    command: str,
) -> list[Path]:
    """Write curves.csv, summary.csv, the figure (PNG and SVG) and report.md; return them."""
    from server.simulation.plots import plot_curves

    rows = ordered_curve_rows(config, results)
    summary = summarize(config, rows)
    write_csv(out / CURVES_FILE, CURVE_COLUMNS, rows)
    write_csv(out / SUMMARY_FILE, SUMMARY_COLUMNS, (row.as_dict() for row in summary))
    figures = plot_curves(config, summary, out / config.experiment)
    report = render_report(
        config,
        summary,
        results,
        sessions,
        [path.name for path in figures if path.suffix == ".png"],
        command,
    )
    report_path = out / REPORT_FILE
    atomic_write_text(report_path, report)
    return [out / CURVES_FILE, out / SUMMARY_FILE, *figures, report_path]
