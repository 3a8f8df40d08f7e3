"""Runs on Ray: `python -m relight_core batch` (a CSV manifest of relight / albedo / render / random
jobs, runner.py) and the engine it shares with `render-data` and `autolabel` (engine.py, progress.py).

Names are imported on first use, so that the data commands and their Ray workers can use the engine
without importing the batch's media jobs."""

__all__ = ["BatchOptions", "BatchSummary", "connect", "run_batch"]


def __getattr__(name: str):
    if name in __all__:
        from relight_core.batch import runner

        return getattr(runner, name)
    raise AttributeError(f"module 'relight_core.batch' has no attribute {name!r}")
