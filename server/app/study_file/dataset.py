"""The study's data as a release (``[dataset]``): what only its authors can say about it."""

from __future__ import annotations

from pydantic import Field

from server.app.study_file.base import Table


class DatasetRelease(Table):
    """The study's data as a release (``bam-study export --format croissant``, ``datapackage``,
    ``psych-ds``, ``parquet``): what only the authors can say about it. The export fills
    everything the server knows (platform, dates, counts, pay, consent, pseudonyms, erasures);
    a field left out here is listed as not answered, never made up."""

    title: str | None = Field(
        None,
        min_length=1,
        max_length=300,
        description="The dataset's name (default: the study's title).",
    )
    description: str | None = Field(
        None, min_length=1, description="What the dataset holds and why it was collected."
    )
    license: str | None = Field(
        None,
        min_length=1,
        max_length=100,
        pattern=r"^[A-Za-z0-9.+-]+$",
        description="The data's licence as an SPDX id (CC-BY-4.0, CC0-1.0, ODbL-1.0, ...).",
    )
    url: str | None = Field(
        None,
        pattern=r"^https?://\S+$",
        description="Where the dataset is published (http or https).",
    )
    version: str | None = Field(
        None,
        min_length=1,
        max_length=40,
        description="The release's version (1.0.0), for a dataset published more than once.",
    )
    authors: tuple[str, ...] = Field(
        (), description="The people who collected and curated the data, one string each."
    )
    citation: str | None = Field(
        None, min_length=1, description="How to cite the dataset (a reference or a BibTeX entry)."
    )
    keywords: tuple[str, ...] = Field((), description="Words to find the dataset by.")
    annotator_demographics: str | None = Field(
        None,
        min_length=1,
        description="Who the participants were (Croissant's rai:annotatorDemographics), as far "
        "as the authors know it: the server asks no demographic question.",
    )
    biases: str | None = Field(
        None, min_length=1, description="Known biases of the data (rai:dataBiases)."
    )
    use_cases: str | None = Field(
        None,
        min_length=1,
        description="What the data is for, and what it is not fit for (rai:dataUseCases).",
    )
    social_impact: str | None = Field(
        None, min_length=1, description="The data's possible social impact (rai:dataSocialImpact)."
    )
    limitations: str | None = Field(
        None,
        min_length=1,
        description="Known limits beyond what the server records (rai:dataLimitations), such "
        "as simulated participants.",
    )
