"""The post-study questionnaire (``[questionnaire]``): its questions, each free text, a point
on a labelled scale or one of a few choices."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator

from server.app.study_file.base import Table

QUESTION_ID = r"^[a-z][a-z0-9_]{0,63}$"


def _distinct_texts(value: tuple[str, ...], problem: str) -> tuple[str, ...]:
    if any(not text.strip() for text in value) or len(set(value)) != len(value):
        raise ValueError(problem)
    return value


class _Question(Table):
    id: str = Field(
        pattern=QUESTION_ID,
        description="The question's name in the data (questionnaire_answers.csv): lower-case "
        "letters, digits and '_'.",
    )
    text: str = Field(min_length=1, max_length=1000, description="The question, as shown.")
    required: bool = Field(True, description="The participant must answer it to finish.")


class TextQuestion(_Question):
    """A free-text answer."""

    kind: Literal["text"] = Field(description="text: free text.")
    max_length: int = Field(1000, ge=1, le=10_000, description="Longest answer, in characters.")
    lines: int = Field(4, ge=1, le=20, description="Height of the answer box, in lines.")


class LikertQuestion(_Question):
    """A point on a scale, each point with its label, stored as 1 to the number of points."""

    kind: Literal["likert"] = Field(description="likert: a point on a labelled scale.")
    labels: tuple[str, ...] = Field(
        min_length=2,
        max_length=11,
        description="The scale's points from the first (1) to the last, each with its label.",
    )

    @field_validator("labels")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return _distinct_texts(value, "each point of the scale needs its own, non-empty label")


class ChoiceQuestion(_Question):
    """One of a few answers (multiple choice), stored as the text of the one picked."""

    kind: Literal["choice"] = Field(description="choice: one of the choices.")
    choices: tuple[str, ...] = Field(
        min_length=2, max_length=20, description="The answers offered, in the order shown."
    )

    @field_validator("choices")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return _distinct_texts(value, "each choice must be a different, non-empty text")


Question = Annotated[TextQuestion | LikertQuestion | ChoiceQuestion, Field(discriminator="kind")]


class Questionnaire(Table):
    """Questions asked after the last agent, before the completion code (none by default)."""

    intro: str = Field(
        "Before you get your completion code, please answer a few questions about the study.",
        min_length=1,
        description="Shown above the questions.",
    )
    questions: tuple[Question, ...] = Field(
        default=(),
        max_length=50,
        description="Each a [[questionnaire.questions]] table with kind = 'text', 'likert' or "
        "'choice'.",
    )

    @field_validator("questions")
    @classmethod
    def _unique_ids(cls, value: tuple[Question, ...]) -> tuple[Question, ...]:
        ids = [question.id for question in value]
        if len(set(ids)) != len(ids):
            raise ValueError("two questions have the same id")
        return value

    def largest_answers_bytes(self) -> int:
        """The largest JSON body the answers can take (every character escaped, as \\uXXXX)."""
        size = 256
        for question in self.questions:
            size += 80 + len(question.id)
            if isinstance(question, TextQuestion):
                size += 6 * question.max_length
            elif isinstance(question, ChoiceQuestion):
                size += 6 * max(len(choice) for choice in question.choices)
        return size
