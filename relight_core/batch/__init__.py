"""`python -m relight_core batch`: a CSV manifest of relight / albedo / render / random jobs, run on Ray."""

from relight_core.batch.runner import BatchOptions, BatchSummary, connect, run_batch

__all__ = ["BatchOptions", "BatchSummary", "connect", "run_batch"]
