"""The study's data as a release a reviewer can take, in the standards venues ask for:
Croissant with its Responsible-AI fields (``croissant``), a Frictionless data package
(``datapackage``), a Psych-DS folder (``psych_ds``) and Parquet files with a Hugging Face
dataset card (``parquet``, with the feedback in the unpaired-preference shape: ``feedback``).

Every format is written from the same export tables (``export.tables``) and the same data
dictionary (``export.columns``), so that they cannot disagree: a column's description and
kind are read from its ``Column``, never written twice. What the server knows of the study
(``About``: the platforms, the dates, the participants by status, the exclusions, the pay,
the consent, the pseudonyms and the erasures) is stated from the database and the study file;
what only the authors can say comes from the study file's ``[dataset]`` table, and a question
it leaves open is listed as not answered (``About.unanswered``), never made up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from server.app.export.columns import FILES, SESSION_COLUMNS
from server.app.export.files import DESCRIPTIONS, write_export
from server.app.storage.vocabulary import ParticipantStatus, SessionKind

if TYPE_CHECKING:
    from server.app.study_file import DatasetRelease, StudyConfig

# The formats, each in its own folder under the export's (``all``: the CSVs, the data package
# and Croissant side by side, since both describe those CSVs; Psych-DS and the Hub's layout
# in folders of their own).
RELEASE_FORMATS = ("croissant", "datapackage", "psych-ds", "parquet")
FOLDERS = {"croissant": "", "datapackage": "", "psych-ds": "psych-ds", "parquet": "hugging-face"}
PLATFORM_NAMES = {"mturk": "Amazon Mechanical Turk", "prolific": "Prolific", "lab": "a lab"}
# The Croissant RAI fields only the authors can answer: the [dataset] key of each.
HUMAN_ANSWERS = {
    "rai:annotatorDemographics": "annotator_demographics",
    "rai:dataBiases": "biases",
    "rai:dataUseCases": "use_cases",
    "rai:dataSocialImpact": "social_impact",
}
ABOUT_KEYS = ("license", "url", "citation", "authors")

# file -> its primary key (the columns that name one row).
PRIMARY_KEYS: dict[str, tuple[str, ...]] = {
    "participants": ("participant_id",),
    "sessions": ("session_id",),
    "tutorial_sessions": ("session_id",),
    "episodes": ("episode_id",),
    "events": ("event_id",),
    "evaluations": ("session_id", "update_index"),
    "messages": ("message_id",),
    "attention_checks": ("participant_id", "number"),
    "erasures": ("erasure_id",),
    "quality": ("participant_id",),
}


@dataclass(frozen=True)
class ForeignKey:
    """``file``'s ``columns`` name a row of ``to`` by its ``to_columns``."""

    file: str
    columns: tuple[str, ...]
    to: str
    to_columns: tuple[str, ...]


def _participant(file: str) -> ForeignKey:
    return ForeignKey(file, ("participant_id",), "participants", ("participant_id",))


SESSION_FILES = {SessionKind.STUDY: "sessions", SessionKind.TUTORIAL: "tutorial_sessions"}


def _session(file: str, kind: SessionKind) -> ForeignKey:
    """``file``'s learning sessions of ``kind``: its column of that kind (``SESSION_COLUMNS``,
    empty on the rows of the other kind) names a row of that kind's file."""
    return ForeignKey(file, (SESSION_COLUMNS[kind],), SESSION_FILES[kind], ("session_id",))


# Every reference between files that holds for every row, but an erasure's (its participant
# is gone). An empty cell refers to nothing: an event's session columns are empty outside
# the sessions. An event's episode_index is not a key into episodes.csv: it is empty for
# events between episodes (a mode or task chosen) while their session is not, and a key
# whose columns are partly empty is checked all the same.
FOREIGN_KEYS: tuple[ForeignKey, ...] = (
    *(
        _participant(name)
        for name, columns in FILES.items()
        if name not in ("participants", "erasures")
        and any(column.name == "participant_id" for column in columns)
    ),
    *(_session(name, kind) for name in ("episodes", "events") for kind in SESSION_FILES),
    _session("evaluations", SessionKind.STUDY),
)


def unanswered(dataset: DatasetRelease | None) -> list[str]:
    """The questions a study file's ``[dataset]`` table leaves open: each RAI field only a
    person can answer, then the licence, address, citation and authors."""

    def given(key: str) -> bool:
        return dataset is not None and bool(getattr(dataset, key))

    missing = [rai for rai, key in HUMAN_ANSWERS.items() if not given(key)]
    return missing + [f"[dataset] {key}" for key in ABOUT_KEYS if not given(key)]


@dataclass(frozen=True)
class About:
    """What a release says of the study besides its tables: from the study file (its
    ``[dataset]`` table, consent and payment) and from the tables themselves."""

    tables: dict[str, pd.DataFrame]
    study: StudyConfig | None = None
    pseudonymized: bool = True
    exported_at: datetime = field(default_factory=lambda: datetime.now(UTC))

    @property
    def dataset(self) -> DatasetRelease | None:
        return None if self.study is None else self.study.dataset

    def answer(self, key: str) -> str | None:
        """A ``[dataset]`` value, None when the study file does not give it."""
        value = None if self.dataset is None else getattr(self.dataset, key)
        return value or None

    @property
    def title(self) -> str:
        return self.answer("title") or (self.study.title if self.study else "BAM Study data")

    @property
    def description(self) -> str:
        given = self.answer("description")
        if given:
            return given
        return (
            f"The data of the study '{self.title}' as the BAM Study server recorded it: "
            f"{self.counts_sentence()} Participants taught simulated agents in grid worlds by "
            "demonstrations and by + and - feedback on the agents' tries; every request, "
            "episode and learner update is here."
        )

    @property
    def authors(self) -> tuple[str, ...]:
        return () if self.dataset is None else self.dataset.authors

    @property
    def keywords(self) -> tuple[str, ...]:
        given = () if self.dataset is None else self.dataset.keywords
        return given or ("interactive learning", "learning from demonstration", "human feedback")

    def unanswered(self) -> list[str]:
        return unanswered(self.dataset)

    # What the server knows.
    def status_counts(self) -> dict[str, int]:
        """Participants by latest status, in the flow's order (none left out, zeros too)."""
        status = self.tables["participants"]["status"]
        return {s.value: int((status == s.value).sum()) for s in ParticipantStatus}

    def platforms(self) -> list[str]:
        found = self.tables["participants"]["platform"].dropna().unique()
        return [PLATFORM_NAMES.get(name, name) for name in sorted(found)]

    def timeframe(self) -> tuple[str, str] | None:
        """The first arrival and the latest request, as ISO 8601 (UTC); None: nobody came."""
        participants = self.tables["participants"]
        times = pd.concat([participants["arrived_at"], participants["last_seen_at"]]).dropna()
        if times.empty:
            return None
        parsed = pd.to_datetime(times, utc=True, format="ISO8601")
        return parsed.min().isoformat(), parsed.max().isoformat()

    def counts_sentence(self) -> str:
        participants = self.tables["participants"]
        counted = ", ".join(f"{n} {s}" for s, n in self.status_counts().items() if n)
        excluded = int(participants["excluded"].fillna(False).astype(bool).sum())
        erased = len(self.tables["erasures"])
        return (
            f"{len(participants)} participants ({counted or 'none'}), {excluded} of them "
            f"excluded by the experimenter, {erased} erased on request, "
            f"{len(self.tables['sessions'])} learning sessions, {len(self.tables['events'])} "
            "events."
        )

    def exclusions(self) -> str:
        participants = self.tables["participants"]
        excluded = participants[participants["excluded"].fillna(False).astype(bool)]
        if excluded.empty:
            return "The experimenter excluded nobody."
        reasons = excluded["exclusion_reason"].fillna("no reason given").value_counts()
        listed = "; ".join(f"{reason} ({count})" for reason, count in reasons.items())
        return f"The experimenter excluded {len(excluded)} participant(s): {listed}."

    def pay(self) -> str:
        parts = []
        if self.study is not None:
            parts.append(f"Payment as shown with the consent: {self.study.payment.strip()}")
            if self.study.prolific is not None:
                parts.append(
                    f"Reward on Prolific: {self.study.prolific.reward} per participant "
                    f"for an estimated {self.study.prolific.estimated_minutes} minutes."
                )
        bonuses = self.tables["bonuses"]
        paid = bonuses[bonuses["payment_state"] == "paid"]
        if paid.empty:
            parts.append("No bonus was paid.")
        else:
            totals = paid.assign(amount=paid["amount"].astype(float)).groupby("currency")["amount"]
            summed = ", ".join(
                f"{total:.2f} {currency}" for currency, total in totals.sum().items()
            )
            parts.append(
                f"Bonuses paid to {paid['participant_id'].nunique()} participant(s): {summed}."
            )
        return " ".join(parts)

    def consent(self) -> str | None:
        return None if self.study is None else self.study.consent.strip()

    def personal_information(self) -> str:
        pseudonyms = (
            "MTurk and Prolific ids are pseudonymised (w_ and a_ followed by a salted HMAC-SHA256 "
            "of the id, with a secret the release does not hold) and completion codes left out"
            if self.pseudonymized
            else "MTurk and Prolific ids and completion codes are as the platforms gave them "
            "(not pseudonymised: keep this release private)"
        )
        erased = len(self.tables["erasures"])
        return (
            f"{pseudonyms}. No name, e-mail, address, IP address or demographic answer is "
            "recorded; free-text answers to the questionnaire (questionnaire_answers.csv) may "
            "hold what a participant chose to write. "
            + (
                f"{erased} participant(s) asked for their data to be erased: every row of theirs "
                "is gone from every file; erasures.csv keeps their pseudonyms so that copies "
                "exported before can be cleaned."
                if erased
                else "No participant asked for their data to be erased."
            )
        )

    def missing_data(self) -> str:
        counts = self.status_counts()
        ended = ", ".join(
            f"{counts[s]} {s}"
            for s in (
                "declined",
                "returned",
                "abandoned",
                "arrived",
                "consented",
                "tutorial",
                "teaching",
                "questionnaire",
            )
            if counts.get(s)
        )
        return (
            f"Not every participant completed: {ended or 'none stopped early'}; their rows are "
            "kept up to where they stopped (participants.csv status, status_changes.csv). "
            f"{self.exclusions()} Excluded participants are kept and marked (participants.csv "
            "excluded, exclusion_reason). Empty cells are values not recorded (a time not "
            "reached, a session not begun). "
            f"{len(self.tables['erasures'])} participant(s) erased on request are missing "
            "altogether."
        )

    def limitations(self) -> str:
        known = self.answer("limitations")
        stated = (
            "The participants are crowd workers or lab volunteers who chose the study; the "
            "environments are small grid worlds."
        )
        return f"{known} {stated}" if known else stated

    def rai(self) -> dict[str, object]:
        """The Croissant RAI fields: the server's facts, then the authors' answers given."""
        collection = (
            f"Participants arrived through {', '.join(self.platforms()) or 'no platform yet'} "
            "and took part in a web study run by the BAM Study server: after consent and a "
            "tutorial they taught simulated agents in grid worlds by demonstrating moves and "
            "giving + or - feedback on the agents' tries, and the server logged every request "
            f"and learner update. {self.counts_sentence()} {self.pay()}"
        )
        consent = self.consent()
        if consent:
            collection += f" Consent text participants agreed to: {consent}"
        kinds = ["Experiments", "Software Collection"]
        if self.study is not None and self.study.questionnaire.questions:
            kinds.append("Surveys")
        fields: dict[str, object] = {
            "rai:dataCollection": collection,
            "rai:dataCollectionType": kinds,
            "rai:dataCollectionMissingData": self.missing_data(),
            "rai:dataCollectionRawData": "The study database; this release is its export "
            "(every request is in events.csv).",
            "rai:dataAnnotationPlatform": self.platforms() or ["none yet"],
            "rai:dataAnnotationProtocol": "Participants labelled the agents' moves with + and - "
            "while teaching (events.csv kind feedback), in the study's own pages.",
            "rai:personalSensitiveInformation": self.personal_information(),
            "rai:dataLimitations": self.limitations(),
        }
        frame = self.timeframe()
        if frame is not None:
            fields["rai:dataCollectionTimeframe"] = list(frame)
        for rai, key in HUMAN_ANSWERS.items():
            answer = self.answer(key)
            if answer:
                fields[rai] = answer
        return fields


def file_description(name: str) -> str:
    return DESCRIPTIONS[name]


Writer = Callable[[About, Path], list[Path]]


def writers() -> dict[str, Writer]:
    from server.app.export.release import croissant, datapackage, parquet, psych_ds

    return {
        "croissant": croissant.write,
        "datapackage": datapackage.write,
        "psych-ds": psych_ds.write,
        "parquet": parquet.write,
    }


def write_release(about: About, out: Path, formats: tuple[str, ...]) -> list[Path]:
    """Write each of ``formats`` (``RELEASE_FORMATS``; ``csv`` too) into ``out`` (or its
    folder under it, ``FOLDERS``); returns the files written."""
    unknown = sorted(set(formats) - {"csv", *RELEASE_FORMATS})
    if unknown:
        raise ValueError(f"unknown format(s) {', '.join(unknown)}")
    written: list[Path] = []
    if {"csv", "croissant", "datapackage"} & set(formats):
        written += write_export(about.tables, out)
    for name, write in writers().items():
        if name in formats:
            written += write(about, out / FOLDERS[name] if FOLDERS[name] else out)
    return written
