"""The study file's former module path: ``server.app.study_file`` is the study file's schema
and loader, and this module gives its names to the importers that still use this path."""

from __future__ import annotations

from server.app.study_file import *  # noqa: F403
from server.app.study_file import __all__ as __all__
