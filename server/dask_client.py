"""A connection to a Dask distributed scheduler (the optional ``bam-study[dask]`` extra), for
the simulations' jobs (``bam-study simulate --scheduler``) and the study server's learner
updates (``BAM_UPDATE_SCHEDULER``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from distributed import Client


class SchedulerError(ValueError):
    """Dask is not installed, or its scheduler cannot be reached: one line, naming the
    address."""


def connect(address: str, timeout: float = 30.0, what: str = "--scheduler") -> Client:
    """A client of the scheduler at ``address``; ``what`` names the setting in the error."""
    try:
        from distributed import Client
    except ImportError:
        raise SchedulerError(
            f"{what} needs Dask distributed, an optional extra: pip install 'bam-study[dask]'"
        ) from None
    try:
        return Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError, TypeError) as error:
        reason = " ".join(str(error).split()) or type(error).__name__
        raise SchedulerError(
            f"cannot connect to the Dask scheduler at {address}: {reason}"
        ) from None
